"""Floods during a session: what a stranger's datagrams cost the teleoperator's 1 kHz loop.

A teleoperator and an operator run as two real processes on 127.0.0.1 (UDP, ``eds:50``, 2 DoF) and a
flood process sends the teleoperator ``rate`` datagrams a second of one class for the session's
length; baseline sessions without a flood run in the same invocation, one before the floods of
each transport and one after each class, and a case's p99 is held to their median.  Classes:

* ``random``: 100 random bytes;
* ``big_handshake``: 60 000 bytes behind a valid handshake-key header (refused by length);
* ``big_session``: 60 000 bytes behind a valid session-key header (refused by length);
* ``recorded_hello``: authentic hellos recorded from 200 earlier handshakes (they hold the key),
  replayed from the flood's own address (rate-limited, then retries or nothing).
* ``zenoh_oversize``: the same session over Zenoh (peers on 127.0.0.1 TCP) and a stranger that
  connects to the teleoperator's Zenoh endpoint and publishes 60 000-byte samples on the session's
  forward key; its ratio is to a Zenoh baseline run in the same invocation.  The stranger holds no
  key, so the teleoperator's Zenoh admission (``transport.zenoh.open_session``) refuses its link
  and no sample reaches the subscriber callback (``transport_oversize`` counts any that did, refused
  there by length, ``ZenohTransport.max_datagram``).

Per case, from the teleoperator's ROLE.json: the loop's lateness p99 (and its ratio to the
baseline's), the process's CPU (and its ratio to the baselines' median), overruns, link-lost events,
the energy margins, the log's dropped chunks, what the endpoint refused (oversize, throttled), what
the transport refused by length, the socket's receive buffer (asked and obtained) and the kernel's
drops on it (SO_MEMINFO at the session's end: what its socket filter refused and what a full buffer
dropped), the host's full-buffer drops over the session (``/proc/net/snmp``), the filter's state;
and the rate the flood reached (sends attempted).
Every datagram goes to 127.0.0.1 only; each flood is bounded in count and time.

``--start`` measures something else (issue 49 item 6): a session *start* under a flood from many
source ports (``--ports``, 2000 by default), which no address filter can refuse before the operator
is known.  A teleoperator waits for an operator; the flood begins; one second later an operator
starts a 1 s session.  Per case: whether the session started, the operator's handshake time
(``waited_for_session_s``: from its endpoint's creation to the confirmed start) against the clean
starts' median, the wall time from its launch to its exit, and what the kernel dropped (the
teleoperator's ``kernel_drops``: its socket filter's refusals and a full buffer's; the host's
``RcvbufErrors``).  Classes: ``junk_handshake`` (a valid handshake-key header, 100 random bytes, a
tag that fails: what anyone can send) and ``recorded_hello`` (authentic hellos an eavesdropper
recorded).  The host's load average is recorded before and after: on a shared host the figure is
that host's, not the stack's alone.

    python -m bench.flood [--rates 10000 50000 100000] [--duration 8] [--out bench/results/flood.json]
    python -m bench.flood --start [--ports 2000] [--rates 30000 100000] [--out bench/results/flood_start.json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing as mp
import os
import platform
import secrets
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench import write_result
from teleop.session import auth, protocol

LOOPBACK = "127.0.0.1"
TELEOP = [sys.executable, "-m", "teleop.cli"]
UDP_CLASSES = ("random", "big_handshake", "big_session", "recorded_hello")
ZENOH_CLASSES = ("zenoh_oversize",)
CLASSES = UDP_CLASSES + ZENOH_CLASSES
START_CLASSES = ("junk_handshake", "recorded_hello")
#: ``--start``: the operator launches this long after the flood began (s), and runs this long a session.
START_AFTER_FLOOD_S, START_SESSION_S = 1.0, 1.0
ZENOH_PREFIX = "bench/flood"
ZENOH_SAMPLE_BYTES = 60_000


def _free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind((LOOPBACK, 0))
        return int(s.getsockname()[1])


def _rcvbuf_errors() -> int:
    """Datagrams the host's UDP dropped for a full receive buffer (``/proc/net/snmp``'s
    ``RcvbufErrors``, every socket): a socket filter's refusals are not among them."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        rows = [
            line.split()
            for line in Path("/proc/net/snmp").read_text().splitlines()
            if line.startswith("Udp:")
        ]
        return int(rows[1][rows[0].index("RcvbufErrors")])
    return 0


def recorded_hellos(psk: bytes, n: int = 200) -> list[bytes]:
    """Authentic hellos of ``n`` handshakes, as an eavesdropper would have recorded them."""
    key = auth.robot_key(psk, auth.DEFAULT_ROBOT_NAME)
    out = []
    for i in range(n):
        p = protocol.SessionParams(
            session=1000 + i,
            codec="eds:50",
            scenario="protocol",
            dof=2,
            b=20.0,
            full_scale=2.0,
            duration=15.0,
        )
        hs = protocol.OperatorHandshake(
            p, now_ns=1 + i, timeout_s=1.0, psk=key, nonce=secrets.token_bytes(16)
        )
        out += hs.poll(1 + i)
    return out


def payloads(kind: str, psk: bytes) -> list[bytes]:
    if kind == "random":
        return [secrets.token_bytes(100) for _ in range(64)]
    if kind == "big_handshake":
        return [b"T\x10" + (i + 1).to_bytes(8, "big") + secrets.token_bytes(60_000) for i in range(8)]
    if kind == "big_session":
        return [b"T\x12" + (i + 1).to_bytes(8, "big") + secrets.token_bytes(60_000) for i in range(8)]
    if kind == "junk_handshake":  # passes every length and kind check; only its MAC fails
        return [b"T\x10" + (i + 1).to_bytes(8, "big") + secrets.token_bytes(116) for i in range(64)]
    return recorded_hellos(psk)


def _paced(send: Callable[[int], None], rate: float, seconds: float, stop: Any = None) -> int:
    """Call ``send(n)`` ``rate`` times a second for ``seconds`` (or until ``stop.value`` is set), in
    batches of at most 64 with the clock read between them (a sender slower than ``rate`` once sent
    its whole backlog in one batch, past its end); it sleeps 0.5 ms when it is ahead.  Returns the
    count."""
    n, t0 = 0, time.monotonic()
    end = t0 + seconds
    batch = 64
    while (now := time.monotonic()) < end and not (stop is not None and stop.value):
        due = int((now - t0) * rate)
        for _ in range(min(due - n, batch)):
            send(n)
            n += 1
        if n >= due:
            time.sleep(0.0005)
    return n


def flood(
    port: int,
    kind: str,
    data: list[bytes],
    rate: float,
    start_at: float,
    end_at: float,
    sent: Any,
    secs: Any,
    cpus: set[int] | None = None,
    sink: bool = False,
    ports: int = 1,
    stop: Any = None,
) -> None:
    """The flood process: ``rate`` datagrams a second of ``data`` (``payloads(kind)``, made by the
    parent before the session) to 127.0.0.1:``port`` (a UDP port, or for ``zenoh_oversize`` the
    teleoperator's Zenoh TCP endpoint) from ``start_at`` until ``end_at`` on the monotonic clock
    (shared by the processes).  The process starts before the session, so its interpreter's start
    and the payloads' making (200 handshakes) do not land in the measured loop's ticks.  The count
    it reached goes to ``sent``, the seconds it flooded to ``secs``.

    ``sink`` (the control, ``--control``): the same datagrams at the same rate to a socket of the
    flood's own whose socket filter drops them all, so the kernel does the same work per datagram
    (the send, the loopback receive, one filter run) and nothing reaches the session: what the
    session's lateness loses then is the attacker's CPU on this 2-core host, not what the endpoint
    spends refusing.

    ``ports``: send from that many sockets of 127.0.0.1 in turn (a source port each), as a flood from
    many addresses would; ``stop``: a shared flag that ends the flood early once set."""
    if cpus is not None:
        os.sched_setaffinity(0, cpus)
    time.sleep(max(0.0, start_at - time.monotonic()))
    t0 = time.monotonic()
    if kind in ZENOH_CLASSES:
        sent.value = _zenoh_flood(port, rate, end_at - t0)
        secs.value = time.monotonic() - t0
        return
    socks = []
    for _ in range(max(1, ports)):
        sk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sk.bind((LOOPBACK, 0))
        socks.append(sk)
    if sink:
        from transport import sockfilter

        drop_all = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        drop_all.bind((LOOPBACK, 0))
        sockfilter.attach(drop_all, [sockfilter.Insn(0x06, 0, 0, sockfilter.DROP)])  # BPF "ret #0"
        port = drop_all.getsockname()[1]

    def send(n: int) -> None:
        with contextlib.suppress(OSError):  # a full socket buffer: the kernel drops, we go on
            socks[n % len(socks)].sendto(data[n % len(data)], (LOOPBACK, port))

    sent.value = _paced(send, rate, end_at - t0, stop)
    secs.value = time.monotonic() - t0
    for sk in socks:
        sk.close()


def _zenoh_flood(port: int, rate: float, seconds: float) -> int:
    """A stranger joins the teleoperator's Zenoh endpoint and publishes oversize samples on the
    session's forward key (what the teleoperator subscribes to)."""
    import zenoh

    from transport.zenoh import make_config

    config = make_config("peer", connect=[f"tcp/{LOOPBACK}:{port}"])
    session: Any = zenoh.open(config)
    try:
        pub = session.declare_publisher(f"{ZENOH_PREFIX}/forward")
        samples = [secrets.token_bytes(ZENOH_SAMPLE_BYTES) for _ in range(8)]

        def send(n: int) -> None:
            with contextlib.suppress(zenoh.ZError):
                pub.put(samples[n % len(samples)])

        return _paced(send, rate, seconds)
    finally:
        session.close()


def _transport_args(transport: str, role: str, port: int) -> list[str]:
    """The command line of one side: UDP on ``port``, or Zenoh peers meeting at TCP ``port``."""
    if transport == "zenoh":
        ep = f"tcp/{LOOPBACK}:{port}"
        where = ["--zenoh-listen", ep] if role == "teleoperator" else ["--zenoh-connect", ep]
        return ["--transport", "zenoh", "--zenoh-prefix", ZENOH_PREFIX, *where]
    if role == "teleoperator":
        return ["--listen", f"{LOOPBACK}:{port}"]
    return ["--peer", f"{LOOPBACK}:{port}", "--listen", f"{LOOPBACK}:0"]


#: ``--pin``: the session's processes (and their log writers) on CPU 0, the flood on CPU 1, as on a
#: robot whose real-time loops have a core of their own and a flood arrives through a NIC whose
#: interrupts another core serves.  On loopback the receive path (the socket filter included) runs in
#: the *sender's* time, so unpinned the bench's own attacker competes with the loops for the two
#: cores, which a remote attacker would not.
SESSION_CPUS, FLOOD_CPUS = {0}, {1}


def _pinned(pin: bool) -> Callable[[], None] | None:
    return (lambda: os.sched_setaffinity(0, SESSION_CPUS)) if pin else None


def session(
    key_file: str,
    psk: bytes,
    kind: str | None,
    rate: float,
    duration: float,
    transport: str = "udp",
    rcvbuf_kib: int | None = None,
    pin: bool = False,
    sink: bool = False,
) -> dict[str, Any]:
    """One session of ``duration`` s over ``transport``, flooded (``kind``) from 1 s after its start,
    or not; with ``sink``, the flood goes to a drop-all socket of its own instead (``flood``)."""
    data = payloads(kind, psk) if kind is not None and kind not in ZENOH_CLASSES else None
    port = _free_port(socket.SOCK_STREAM if transport == "zenoh" else socket.SOCK_DGRAM)
    ctx = mp.get_context("spawn")  # a fresh interpreter: no copy of this one's threads or locks
    sent, secs = ctx.Value("q", 0), ctx.Value("d", 0.0)
    proc = None
    t0 = time.monotonic()  # the operator starts 1.5 s after the teleoperator, the session soon after
    if kind is not None:  # started first, so its interpreter's start lands before the session's ticks
        start_at, end_at = t0 + 3.0, t0 + 1.5 + duration - 0.5  # before the session's end
        cpus = FLOOD_CPUS if pin else None
        args = (port, kind, data or [], rate, start_at, end_at, sent, secs, cpus, sink)
        proc = ctx.Process(target=flood, args=args, daemon=True)
        proc.start()
    with tempfile.TemporaryDirectory(prefix="teleop-flood-") as tmp:
        logs = Path(tmp) / "logs"
        to = subprocess.Popen(
            [*TELEOP, "teleoperator", "--key-file", key_file,
             *_transport_args(transport, "teleoperator", port), "--log", str(logs), "--quiet",
             *(["--udp-rcvbuf", str(rcvbuf_kib)] if rcvbuf_kib is not None else [])],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, preexec_fn=_pinned(pin),
        )  # fmt: skip
        time.sleep(max(0.0, t0 + 1.5 - time.monotonic()))
        op = subprocess.Popen(
            [*TELEOP, "operator", "--key-file", key_file, *_transport_args(transport, "operator", port),
             "--codec", "eds:50", "--duration", str(duration), "--quiet"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, preexec_fn=_pinned(pin),
        )  # fmt: skip
        overflow0 = _rcvbuf_errors()
        rc_op = op.wait(timeout=duration + 60)
        if proc is not None:
            proc.join(10)
        overflow = _rcvbuf_errors() - overflow0
        rc_to = to.wait(timeout=60)
        summary = (
            json.loads((logs / "teleoperator.json").read_text())
            if (logs / "teleoperator.json").exists()
            else {}
        )
    loop = summary.get("loop") or {}
    pv = summary.get("passivity") or {}
    log = summary.get("log") or {}
    rx = summary.get("received") or {}
    return {
        "class": kind or ("baseline" if transport == "udp" else f"baseline_{transport}"),
        "transport": transport,
        "rate": rate if kind else 0,
        "sent": int(sent.value),
        "flood_s": round(float(secs.value), 3),  # how long it flooded (it starts after its interpreter)
        "exit_codes": {"operator": rc_op, "teleoperator": rc_to},
        "completed": summary.get("completed"),
        "lateness_p99_us": (loop.get("lateness_us") or {}).get("p99"),
        "period_error_p99_us": (loop.get("period_error_us") or {}).get("p99"),
        # The teleoperator process's CPU (user and system, its threads included) over its wall time:
        # what refusing the flood costs the endpoint itself, far steadier than a p99 on a shared host.
        "cpu_fraction": loop.get("cpu_fraction"),
        "overruns": loop.get("overruns"),
        "link_lost_events": pv.get("link_lost_events"),
        "min_margin_J": pv.get("min_margin"),
        "log_dropped_chunks": log.get("dropped_chunks"),
        "oversize_refused": summary.get("oversize_refused"),
        "handshake_throttled": summary.get("handshake_throttled"),
        "transport_oversize": rx.get("oversize"),
        "foreign": rx.get("foreign"),
        # SO_MEMINFO at the session's end (None: not UDP): what the socket's filter refused and what a
        # full buffer dropped; the latter alone (host-wide) in rcvbuf_errors.  (/proc/net/udp, read
        # here before, lost the socket when the teleoperator exited first.)
        "kernel_drops": rx.get("kernel_drops"),
        "rcvbuf_errors": overflow,
        "rcvbuf_asked": rx.get("rcvbuf_asked"),
        "rcvbuf_bytes": rx.get("rcvbuf_bytes"),
        "drain_budget_hits": rx.get("drain_budget_hits"),
        "filter": rx.get("filter"),
        "warnings": summary.get("warnings"),
    }


def start_session(
    key_file: str,
    psk: bytes,
    kind: str | None,
    rate: float,
    ports: int,
    rcvbuf_kib: int | None = None,
    connect_timeout: float = 10.0,
) -> dict[str, Any]:
    """One session start under a flood of ``kind`` from ``ports`` source ports (``--start``), or
    without one (``kind`` None): the flood begins once the teleoperator waits, the operator
    :data:`START_AFTER_FLOOD_S` later; the flood ends when the operator has exited."""
    data = payloads(kind, psk) if kind is not None else []
    port = _free_port()
    ctx = mp.get_context("spawn")
    sent, secs, stop = ctx.Value("q", 0), ctx.Value("d", 0.0), ctx.Value("b", False)
    t0 = time.monotonic()
    flood_at = t0 + 2.0  # the teleoperator's interpreter is up and waiting by then
    op_at = flood_at + START_AFTER_FLOOD_S
    proc = None
    if kind is not None:
        end_at = op_at + connect_timeout + START_SESSION_S + 10.0  # the stop flag ends it first
        args = (port, kind, data, rate, flood_at, end_at, sent, secs, None, False, ports, stop)
        proc = ctx.Process(target=flood, args=args, daemon=True)
        proc.start()
    with tempfile.TemporaryDirectory(prefix="teleop-flood-start-") as tmp:
        logs, ologs = Path(tmp) / "logs", Path(tmp) / "ologs"
        to = subprocess.Popen(
            [*TELEOP, "teleoperator", "--key-file", key_file, "--listen", f"{LOOPBACK}:{port}",
             "--log", str(logs), "--quiet", "--wait", str(connect_timeout + 15),
             *(["--udp-rcvbuf", str(rcvbuf_kib)] if rcvbuf_kib is not None else [])],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        time.sleep(max(0.0, op_at - time.monotonic()))
        overflow0 = _rcvbuf_errors()
        launched = time.monotonic()
        op = subprocess.Popen(
            [*TELEOP, "operator", "--key-file", key_file, "--peer", f"{LOOPBACK}:{port}",
             "--listen", f"{LOOPBACK}:0", "--codec", "eds:50", "--duration", str(START_SESSION_S),
             "--connect-timeout", str(connect_timeout), "--log", str(ologs), "--quiet"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        _, op_err = op.communicate(timeout=connect_timeout + START_SESSION_S + 60)
        wall = time.monotonic() - launched
        stop.value = True
        if proc is not None:
            proc.join(10)
        overflow = _rcvbuf_errors() - overflow0
        if to.poll() is None:
            to.terminate()  # no session came: it would wait on
        _, to_err = to.communicate(timeout=30)
        o = _json(ologs / "operator.json")
        t = _json(logs / "teleoperator.json")
    orx, trx = o.get("received") or {}, t.get("received") or {}
    return {
        "class": kind or "clean",
        "rate": rate if kind else 0,
        "ports": ports if kind else 0,
        "sent": int(sent.value),
        "flood_s": round(float(secs.value), 3),
        "operator_rc": op.returncode,
        "started": op.returncode == 0 and bool(o.get("completed")),
        "handshake_s": o.get("waited_for_session_s"),
        "launch_to_exit_s": round(wall, 3),
        "handshake_rtt_us": o.get("handshake_rtt_us"),
        "operator_error": (op_err or "").strip().splitlines()[-1:] or None,
        "to_kernel_drops": trx.get("kernel_drops"),
        "to_rcvbuf_bytes": trx.get("rcvbuf_bytes"),
        "to_handshake_throttled": t.get("handshake_throttled"),
        "to_security": t.get("security"),
        "operator_kernel_drops": orx.get("kernel_drops"),
        "rcvbuf_errors": overflow,
        "to_stderr_tail": (to_err or "").strip().splitlines()[-2:],
    }


def _json(path: Path) -> dict[str, Any]:
    with contextlib.suppress(OSError, ValueError):
        doc = json.loads(path.read_text())
        return doc if isinstance(doc, dict) else {}
    return {}


def _load() -> dict[str, float]:
    """The host's load average (``uptime``'s three figures): the bench shares its host."""
    one, five, fifteen = os.getloadavg()
    return {"1min": one, "5min": five, "15min": fifteen}


def main_start(a: argparse.Namespace, argv: list[str] | None) -> int:
    """``--start``: session starts under floods from many ports against clean starts (issue 49)."""
    psk = auth.generate_key()
    load_before = _load()
    clean: list[dict[str, Any]] = []
    cases: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="teleop-flood-key-") as kd:
        key_file = str(Path(kd) / "k")
        auth.write_key_file(key_file, psk)

        def show(c: dict[str, Any]) -> None:
            print(
                f"{c['class']:15s} {c['rate']:8.0f}/s from {c['ports']} ports: started {c['started']},"
                f" handshake {c['handshake_s']} s, launch to exit {c['launch_to_exit_s']} s, TO kernel"
                f" drops {c['to_kernel_drops']}, host full-buffer drops {c['rcvbuf_errors']}",
                flush=True,
            )

        for _ in range(a.repeats):
            clean.append(start_session(key_file, psk, None, 0, 0, a.udp_rcvbuf))
            show(clean[-1])
        for kind in a.classes:
            for rate in a.rates:
                for _ in range(a.repeats):
                    cases.append(start_session(key_file, psk, kind, rate, a.ports, a.udp_rcvbuf))
                    show(cases[-1])
        clean.append(start_session(key_file, psk, None, 0, 0, a.udp_rcvbuf))  # and one after
        show(clean[-1])
    hs = [c["handshake_s"] for c in clean if c["started"] and c["handshake_s"] is not None]
    ref = statistics.median(hs) if hs else None
    for c in cases:
        c["handshake_ratio"] = c["handshake_s"] / ref if ref and c["started"] and c["handshake_s"] else None
        c["within_2x"] = c["handshake_ratio"] is not None and c["handshake_ratio"] <= 2.0
    out = {
        "host": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "shared": True,  # a host other work ran on: its load average below
            "load_before": load_before,
            "load_after": _load(),
        },
        "command": "python -m bench.flood " + " ".join(argv if argv is not None else sys.argv[1:]),
        "ports": a.ports,
        "session_s": START_SESSION_S,
        "operator_after_flood_s": START_AFTER_FLOOD_S,
        "udp_rcvbuf_kib": a.udp_rcvbuf,
        "repeats": a.repeats,
        "clean": clean,
        "clean_handshake_s": ref,
        "cases": cases,
        "within_2x": sum(c["within_2x"] for c in cases),
        "cases_run": len(cases),
    }
    path = Path(a.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_result(path, out)
    print(f"{out['within_2x']} of {out['cases_run']} starts within 2x of clean ({ref} s); wrote {path}")
    return 0


def _reference(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The baseline a transport's cases are held to: its first run's figures, with the lateness p99
    the median of all its runs (one before the floods and one after each class: a single quiet
    session's p99 on a shared 2-core host varied 7-215 us)."""
    p99s = [r["lateness_p99_us"] for r in runs if r["lateness_p99_us"] is not None]
    ref = dict(runs[0])
    ref["lateness_p99_us"] = statistics.median(p99s) if p99s else None
    ref["lateness_p99_us_runs"] = p99s
    cpus = [r["cpu_fraction"] for r in runs if r.get("cpu_fraction") is not None]
    ref["cpu_fraction"] = statistics.median(cpus) if cpus else None
    ref["runs"] = len(runs)
    ref["link_lost_events"] = max((r["link_lost_events"] or 0) for r in runs)
    ref["log_dropped_chunks"] = max((r["log_dropped_chunks"] or 0) for r in runs)
    return ref


def _combine(reps: list[dict[str, Any]]) -> dict[str, Any]:
    """One case from its repeats: the run of median lateness p99 (its figures), every run's p99, and
    the worst of the runs for what must hold in each (link lost, log chunks dropped, margins)."""
    order = sorted(
        reps, key=lambda r: r["lateness_p99_us"] if r["lateness_p99_us"] is not None else float("inf")
    )
    c = dict(order[(len(order) - 1) // 2])
    c["lateness_p99_us_runs"] = [r["lateness_p99_us"] for r in reps]
    cpus = [r["cpu_fraction"] for r in reps if r.get("cpu_fraction") is not None]
    c["cpu_fraction"] = statistics.median(cpus) if cpus else None
    c["link_lost_events"] = max((r["link_lost_events"] or 0) for r in reps)
    c["log_dropped_chunks"] = max((r["log_dropped_chunks"] or 0) for r in reps)
    c["min_margin_J"] = min((r["min_margin_J"] or 0.0) for r in reps)
    c["completed"] = all(r["completed"] for r in reps)
    return c


def _print_case(c: dict[str, Any]) -> None:
    reached = c["sent"] / c["flood_s"] if c.get("flood_s") else 0.0
    print(
        f"{c['class']:15s} {c['rate']:8.0f}/s reached {reached:8.0f}/s  p99 {c['lateness_p99_us']} us"
        f"  link lost {c['link_lost_events']}  dropped chunks {c['log_dropped_chunks']}"
        f"  kernel drops {c['kernel_drops']} (full buffer {c['rcvbuf_errors']})"
        f"  oversize {c['oversize_refused']}/{c['transport_oversize']} (endpoint/transport)"
        f"  throttled {c['handshake_throttled']}",
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.flood", description=__doc__.split("\n\n")[0])
    ap.add_argument("--rates", type=float, nargs="+", default=[10_000.0, 50_000.0, 100_000.0])
    ap.add_argument("--classes", nargs="+", choices=CLASSES + START_CLASSES, help="default: every class")
    ap.add_argument("--duration", type=float, default=8.0, help="seconds of each session (>= 4)")
    ap.add_argument(
        "--udp-rcvbuf", type=int, metavar="KIB", help="the teleoperator's --udp-rcvbuf (default: its own)"
    )
    ap.add_argument(
        "--pin", action="store_true", help="the session on CPU 0, the flood on CPU 1 (see SESSION_CPUS)"
    )
    ap.add_argument("--repeats", type=int, default=1, help="sessions per case; its p99 is their median")
    ap.add_argument(
        "--control",
        action="store_true",
        help="also run each UDP case's flood into a drop-all socket of the flood's own (flood: sink)",
    )
    ap.add_argument("--start", action="store_true", help="session starts under a flood from many ports")
    ap.add_argument("--ports", type=int, default=2000, help="--start: source ports the flood sends from")
    ap.add_argument("--out", help="default bench/results/flood.json (--start: flood_start.json)")
    a = ap.parse_args(argv)
    if a.start:
        a.out = a.out or "bench/results/flood_start.json"
        a.classes = [c for c in a.classes or START_CLASSES if c in START_CLASSES]
        if not 1 <= a.ports <= 10_000:
            ap.error("--ports must be 1 to 10000")
        return main_start(a, argv)
    a.out = a.out or "bench/results/flood.json"
    a.classes = [c for c in a.classes or CLASSES if c in CLASSES]
    if a.duration < 4:
        ap.error("--duration must be at least 4 s")
    if a.repeats < 1:
        ap.error("--repeats must be at least 1")
    need, have = SESSION_CPUS | FLOOD_CPUS, os.sched_getaffinity(0)
    if a.pin and not have >= need:
        ap.error(f"--pin needs CPUs {sorted(need)}; this process may run on {sorted(have)}")
    psk = auth.generate_key()
    with tempfile.TemporaryDirectory(prefix="teleop-flood-key-") as kd:
        key_file = str(Path(kd) / "k")
        auth.write_key_file(key_file, psk)
        runs: dict[str, list[dict[str, Any]]] = {}

        def run(kind: str | None, rate: float, transport: str, sink: bool = False) -> dict[str, Any]:
            return session(key_file, psk, kind, rate, a.duration, transport, a.udp_rcvbuf, a.pin, sink)

        def baseline(transport: str) -> None:
            base = run(None, 0, transport)
            runs.setdefault(transport, []).append(base)
            print(
                f"baseline ({transport}): lateness p99 {base['lateness_p99_us']} us, overruns"
                f" {base['overruns']}, receive buffer {base['rcvbuf_bytes']} B",
                flush=True,
            )

        cases = []
        for kind in a.classes:
            transport = "zenoh" if kind in ZENOH_CLASSES else "udp"
            if transport not in runs:
                baseline(transport)
            for rate in a.rates:
                reps = []
                for _ in range(a.repeats):
                    reps.append(run(kind, rate, transport))
                    _print_case(reps[-1])
                case = _combine(reps)
                if a.control and transport == "udp":
                    ctl = [run(kind, rate, transport, sink=True) for _ in range(a.repeats)]
                    p99s = [r["lateness_p99_us"] for r in ctl if r["lateness_p99_us"] is not None]
                    case["control_p99_us"] = statistics.median(p99s) if p99s else None
                    case["control_p99_us_runs"] = p99s
                    print(f"{kind:15s} {rate:8.0f}/s  control (into a sink) p99 {p99s} us", flush=True)
                cases.append(case)
            baseline(transport)  # one after each class's rates: the reference is their median
    bases = {t: _reference(r) for t, r in runs.items()}
    for c in cases:
        base_cpu = bases[c["transport"]].get("cpu_fraction")
        c["cpu_ratio"] = c["cpu_fraction"] / base_cpu if base_cpu and c.get("cpu_fraction") else None
        b = bases[c["transport"]]["lateness_p99_us"]
        c["p99_ratio"] = c["lateness_p99_us"] / b if b and c["lateness_p99_us"] is not None else None
        c["within_2x"] = c["p99_ratio"] is not None and c["p99_ratio"] <= 2.0
        c["ok"] = bool(
            c["within_2x"] and c["link_lost_events"] == 0 and (c["min_margin_J"] or 0) >= -1e-9
            and c["log_dropped_chunks"] == 0 and c["completed"]
        )  # fmt: skip
        control = c.get("control_p99_us")
        if control and c["lateness_p99_us"] is not None:  # beyond what the flood's own CPU takes
            c["p99_ratio_control"] = c["lateness_p99_us"] / control
        ratio = "-" if c["p99_ratio"] is None else f"{c['p99_ratio']:.2f}"
        vs = f", x{c['p99_ratio_control']:.2f} of its control" if c.get("p99_ratio_control") else ""
        print(f"{c['class']:15s} {c['rate']:8.0f}/s  p99 x{ratio} of the baselines' median{vs}", flush=True)
    out = {
        "host": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
        },
        "command": "python -m bench.flood " + " ".join(argv or sys.argv[1:]),
        "duration_s": a.duration,
        "udp_rcvbuf_kib": a.udp_rcvbuf,
        "repeats": a.repeats,
        "control": a.control,
        "pinned": {"session": sorted(SESSION_CPUS), "flood": sorted(FLOOD_CPUS)} if a.pin else None,
        "baseline": bases.get("udp"),
        "baselines": bases,
        "cases": cases,
        "targets_met": sum(c["ok"] for c in cases),
        "cases_run": len(cases),
    }
    path = Path(a.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_result(path, out)
    print(f"{out['targets_met']} of {out['cases_run']} cases within the targets; wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
