"""Issue 49: a handshake-only delayer between two real processes.  200 ms added robot -> operator to
the handshake's datagrams only (welcomes, retries) make NTP's offset 100 ms wrong, so the robot's
tick 0 lands 100 ms before the operator's; PROTOCOL.md 5.1 says the session moves it back.  The
reports show that it does: the operator moved its tick 0 by the 100 ms, and what the robot measures
of the operator's packets is the loopback's transit, not the 100 ms the skew would add.

The delayer is a UDP relay in this test, on 127.0.0.1: the operator talks to it as to the robot.
"""

from __future__ import annotations

import heapq
import json
import select
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from teleop.session import auth

from .waiting import exited_ok

TELEOP = [sys.executable, "-m", "teleop.cli"]
DELAY_S = 0.2


class HandshakeDelayer:
    """Relays between the operator (at ``port``) and the robot at ``robot``; each handshake-key
    datagram the robot sends is held ``delay_s`` (session-key ones, data and ``started``, are not)."""

    def __init__(self, robot: tuple[str, int], delay_s: float) -> None:
        self.robot, self.delay_s = robot, delay_s
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the operator's side
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the robot's side
        for s in (self.front, self.back):
            s.bind(("127.0.0.1", 0))
        self.port = int(self.front.getsockname()[1])
        self.operator: tuple[str, int] | None = None
        self.held: list[tuple[float, int, bytes]] = []
        self.delayed = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        n = 0
        while not self._stop.is_set():
            wait = 0.05 if not self.held else max(0.0, self.held[0][0] - time.monotonic())
            for sock in select.select([self.front, self.back], [], [], wait)[0]:
                data, addr = sock.recvfrom(65536)
                if sock is self.front:
                    self.operator = addr
                    self.back.sendto(data, self.robot)
                    continue
                hdr = auth.peek(data)
                if hdr is not None and hdr[0] == auth.HANDSHAKE:
                    n += 1
                    self.delayed += 1
                    heapq.heappush(self.held, (time.monotonic() + self.delay_s, n, data))
                elif self.operator is not None:
                    self.front.sendto(data, self.operator)
            while self.held and self.held[0][0] <= time.monotonic() and self.operator is not None:
                self.front.sendto(heapq.heappop(self.held)[2], self.operator)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.front.close()
        self.back.close()


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.integration
@pytest.mark.serial
def test_a_handshake_only_delayer_is_put_right_in_session_between_real_processes(
    tmp_path: Path, key: str
) -> None:
    port, logs = _free_port(), tmp_path / "logs"
    to = subprocess.Popen(
        [*TELEOP, "teleoperator", "--key-file", key, "--listen", f"127.0.0.1:{port}", "--log", str(logs),
         "--quiet", "--no-rt", "--wait", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    relay = HandshakeDelayer(("127.0.0.1", port), DELAY_S)
    try:
        op = subprocess.Popen(
            [*TELEOP, "operator", "--key-file", key, "--peer", f"127.0.0.1:{relay.port}",
             "--listen", "127.0.0.1:0", "--codec", "none", "--duration", "3", "--log", str(logs),
             "--quiet", "--no-rt", "--connect-timeout", "30"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        exited_ok(op, timeout=90)
        exited_ok(to, timeout=60)
    finally:
        relay.close()
        for p in (to, locals().get("op")):
            if p is not None and p.poll() is None:
                p.kill()
    summary: dict[str, Any] = {
        role: json.loads((logs / f"{role}.json").read_text()) for role in ("operator", "teleoperator")
    }
    o, t = summary["operator"], summary["teleoperator"]
    print(json.dumps({r: s["clock"] for r, s in summary.items()}, indent=1), o.get("handshake_rtt_us"))
    assert relay.delayed >= 8  # the welcomes (and any retry) went through the delay
    assert o["handshake_rtt_us"] >= DELAY_S * 1e6  # the exchange the start was placed from
    assert o["completed"] and t["completed"]
    # The robot's tick 0 came 100 ms before the operator's: the operator saw the robot's packets
    # arrive before they were sent and moved its own tick 0 back by those 100 ticks (within 2).
    assert 98.0 <= o["clock"]["skew_shift_ms"] <= 102.0, o["clock"]
    assert o["clock"]["skew_shifts"] >= 1 and t["clock"]["skew_shift_ms"] == 0.0
    # ... after which both ends are aligned: the transits each measures of the other's packets are
    # the loopback's and the relay's (a few ms at most on a loaded host, the robot's phase included),
    # not the 100 ms the wrong offset put between the tick 0s.
    for s in (o, t):
        assert -0.5 <= s["clock"]["transit_ms"]["p50"] <= 20.0, s["clock"]
    # The operator had moved before its first packet left: not the 100 ms a late move would show.
    assert t["clock"]["first_transit_ms"] < 20.0, t["clock"]
