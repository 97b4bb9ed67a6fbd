"""The same session over Zenoh: peer to peer, through a router, interoperability, clear errors.

Real processes on loopback with scouting off and explicit endpoints.
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from tests.ran import RAN
from tests.test_processes import _alive
from tests.test_zenoh import readme_subscriber
from tests.waiting import tcp_clients, tcp_listening, wait_for

pytestmark = pytest.mark.integration
TELEOP = [sys.executable, "-m", "teleop.cli"]


def _free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _run(tmp: Path, *args: str) -> tuple[subprocess.CompletedProcess[str], dict[str, Any]]:
    out = tmp / "run"
    r = subprocess.run(
        [*TELEOP, "run", "--transport", "zenoh", "--out", str(out), "--no-plots", "--no-sim", *args],
        capture_output=True,
        text=True,
        timeout=90,
    )
    rep = json.loads((out / "report.json").read_text()) if (out / "report.json").exists() else {}
    return r, rep


@pytest.mark.parametrize("mode", ["peer", "client"])
def test_session_over_zenoh(tmp_path: Path, mode: str) -> None:
    r, rep = _run(tmp_path, "--zenoh-mode", mode, "--codec", "eds:50", "--duration", "3")
    assert r.returncode in RAN, r.stderr
    assert rep["transport"] == "zenoh" and rep["zenoh"]["mode"] == mode
    assert rep["zenoh"]["router_launched"] is (mode == "client")
    for d, sender in (("forward", "operator"), ("backward", "teleoperator")):
        w = rep["wire"][d]
        stalled = rep["processes"][sender]["loop"]["skipped"] > 0  # a host stall shifts eDS's sends
        assert w["received_packets"] == w["packets"]
        if not stalled:
            assert w["packets"] == 60 and w["compression_payload"] == 50.0  # same counts as over UDP
        assert rep["link"][d]["loss"] == 0.0
        assert rep["energy"][d]["min_margin"] >= -1e-9
    for role, p in rep["processes"].items():
        assert p["loop"]["ticks"] + p["loop"]["skipped"] == 3000, role
        assert not _alive(p["pid"]), role
        # Who could open a Zenoh link to it: in peer mode only holders of the robot key.
        received = json.loads((tmp_path / "run" / "logs" / f"{role}.json").read_text())["received"]
        admits = {"peer": "peers holding the robot key (user-password)", "client": "the router's"}
        assert received["admission"] == admits[mode], role
    # This run's router is gone (another run's on the same host, a parallel test's, is not ours).
    ours = f"router --listen {rep['zenoh']['endpoint']}"
    assert ours not in subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True).stdout


def test_plain_subscriber_decodes_live_packets(tmp_path: Path) -> None:
    """A subscriber written from the docs alone (zenoh + msgpack + zlib) decodes a live session."""
    endpoint = f"tcp/127.0.0.1:{_free_tcp_port()}"
    router = subprocess.Popen([*TELEOP, "router", "--listen", endpoint])
    port = int(endpoint.rsplit(":", 1)[1])
    try:
        wait_for(lambda: tcp_listening(port), 60, "the router's listener")
        got: dict[str, Any] = {}

        def listen() -> None:
            got["result"] = readme_subscriber(endpoint, "teleop/*", 20, timeout=20.0, mode="client")

        th = threading.Thread(target=listen)
        th.start()
        wait_for(lambda: tcp_clients(port) >= 1, 60, "the subscriber in the router")
        r, rep = _run(
            tmp_path,
            "--zenoh-mode",
            "client",
            "--zenoh-router",
            endpoint,
            "--codec",
            "none",
            "--duration",
            "2",
        )
        th.join(timeout=30)
        assert r.returncode in RAN, r.stderr
        assert rep["zenoh"]["router_launched"] is False
        packets, controls, bad_crc = got["result"]
        assert len(packets) == 20 and bad_crc == 0 and controls >= 1  # the hello/start went by too
        seqs = [p[4] for p in packets]
        for f in packets:
            assert f[0] == b"TW" and f[1] == 1 and f[2] == rep["session"] and f[3] == 0  # forward
            assert f[7] == 0 and len(f[8]) == 4 and isinstance(f[9], float)  # codec none, 2 DoF x int16
        assert seqs == sorted(seqs) and len(set(seqs)) == 20
    finally:
        router.send_signal(signal.SIGINT)
        router.wait(timeout=10)


def test_unreachable_router_is_a_clear_error() -> None:
    endpoint = f"tcp/127.0.0.1:{_free_tcp_port()}"
    t0 = time.monotonic()
    r = subprocess.run(
        [
            *TELEOP,
            "operator",
            "--insecure",
            "--transport",
            "zenoh",
            "--zenoh-mode",
            "client",
            "--zenoh-router",
            endpoint,
            "--connect-timeout",
            "3",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 1
    assert f"cannot reach Zenoh router at {endpoint}" in r.stderr
    assert time.monotonic() - t0 < 15


def test_a_stranger_on_the_zenoh_key_cannot_drive_the_robot(tmp_path: Path) -> None:
    """Issue 11: any peer that reaches the router can publish on the session's keys.  Its forged,
    replayed and tampered datagrams are refused and counted; the robot plays no more energy than
    the operator sent, and the session completes."""
    import zenoh

    from teleop.session import auth, wire

    endpoint = f"tcp/127.0.0.1:{_free_tcp_port()}"
    router = subprocess.Popen([*TELEOP, "router", "--listen", endpoint])
    sent = {"forged": 0, "replayed": 0, "tampered": 0}
    stop = threading.Event()

    def attack() -> None:
        cfg = zenoh.Config.from_json5(
            json.dumps(
                {
                    "mode": "client",
                    "connect": {"endpoints": [endpoint]},
                    "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
                }
            )
        )
        captured: list[tuple[str, bytes]] = []
        z = zenoh.open(cfg)  # (the router listens: the test waited for it)
        with z:
            z.declare_subscriber(
                "teleop/**", lambda s: captured.append((str(s.key_expr), s.payload.to_bytes()))
            )
            # What the CRC-only wire let through: full-scale waves claiming 1e300 J, far-future seq.
            pkt = wire.Packet(1, wire.FORWARD, 2**31, 2**31, 0, 0, b"\xff\x7f\xff\x7f", 1e300)
            while not stop.is_set():
                fwd = [c for c in captured if c[0].endswith("/forward") and len(c[1]) > 40]
                if fwd:
                    key, genuine = fwd[-1]
                    forged_body = wire.encode(pkt)
                    for data, what in (
                        (auth.Sealer(auth.INSECURE_KEY, auth.SESSION, 0, 10**6).seal(forged_body), "forged"),
                        (genuine, "replayed"),
                        (genuine[:20] + bytes([genuine[20] ^ 1]) + genuine[21:], "tampered"),
                    ):
                        z.put(key, data)
                        sent[what] += 1
                stop.wait(0.002)  # until the session ends, an attack every 2 ms

    try:
        wait_for(lambda: tcp_listening(int(endpoint.rsplit(":", 1)[1])), 60, "the router's listener")
        th = threading.Thread(target=attack)
        th.start()
        r, rep = _run(
            tmp_path,
            "--zenoh-mode",
            "client",
            "--zenoh-router",
            endpoint,
            "--codec",
            "none",
            "--duration",
            "3",
        )
        stop.set()
        th.join(timeout=10)
    finally:
        router.send_signal(signal.SIGINT)
        router.wait(timeout=10)
    assert r.returncode in RAN, r.stderr
    assert min(sent.values()) > 100, sent
    sec = rep["security"]
    assert sec["auth"] == "blake2s-128"
    # Forged and tampered datagrams fail the tag; exact copies are replays.  Most, not all, are
    # counted by the session's port: the attack starts with the first forward datagram (the hello),
    # so some arrive during the handshake (which now also starts the log's writer process) or
    # after the linger, and Zenoh's DROP congestion control may give up on a few.
    assert sec["rejected"]["forward"] >= 0.5 * (sent["forged"] + sent["tampered"])
    assert sec["replayed"]["forward"] >= 0.5 * sent["replayed"]
    assert sec["energy_reports_clamped"]["forward"] == 0  # nothing forged reached the watchdog
    e = rep["energy"]["forward"]
    assert e["played"] <= e["sent"] and e["min_margin"] >= -1e-9
    pv = rep["passivity"]["forward"]  # concealment of missed payloads is scaled to the budget:
    assert pv["controller_active_ticks"] == pv["violations"] and pv["min_margin"] >= -1e-9
    assert rep["processes"]["teleoperator"]["completed"]
