"""Restarts and identity over a real link: two processes through a UDP relay on loopback that delays
every datagram 2 ms each way (a 4 ms round trip, where the rejoin used to fail: it refused answers
slower than 1 ms), a relay to another robot, and systemd's socket activation.

Only loopback is used; the relay is a thread of the test with a bounded life.
"""

from __future__ import annotations

import heapq
import json
import os
import selectors
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from tests.ran import RAN
from tests.test_processes import TELEOP, _free_port, _spawn
from tests.waiting import ticks_logged, udp_bound, wait_for


class DelayRelay:
    """Forwards what reaches ``addr`` to ``target`` after ``delay_s``, and the answers back to the
    last address that sent, after the same delay: a link with a fixed one-way delay."""

    def __init__(self, target: tuple[str, int], delay_s: float, lifetime_s: float = 60.0) -> None:
        self.target, self.delay = target, delay_s
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind(("127.0.0.1", 0))
        self.addr = self.front.getsockname()
        self.client: Any = None
        self.forwarded = 0
        self._end = time.monotonic() + lifetime_s
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self.front, selectors.EVENT_READ)
        sel.register(self.back, selectors.EVENT_READ)
        due: list[tuple[float, int, socket.socket, bytes, Any]] = []
        n = 0
        while not self._stop and time.monotonic() < self._end:
            timeout = max(0.0, due[0][0] - time.monotonic()) if due else 0.05
            for key, _ in sel.select(min(timeout, 0.05)):
                sock: socket.socket = key.fileobj  # type: ignore[assignment]
                data, src = sock.recvfrom(65536)
                n += 1
                if sock is self.front:
                    self.client = src
                    heapq.heappush(due, (time.monotonic() + self.delay, n, self.back, data, self.target))
                elif self.client is not None:
                    heapq.heappush(due, (time.monotonic() + self.delay, n, self.front, data, self.client))
            while due and due[0][0] <= time.monotonic():
                _, _, out, data, dst = heapq.heappop(due)
                out.sendto(data, dst)
                self.forwarded += 1

    def close(self) -> None:
        self._stop = True
        self._thread.join(2)
        self.front.close()
        self.back.close()


def _operator(
    key: str, peer: tuple[str, int], logs: Path, duration: str, *extra: str
) -> subprocess.Popen[str]:
    return _spawn(
        "operator", "--key-file", key, "--peer", f"{peer[0]}:{peer[1]}", "--listen", "127.0.0.1:0",
        "--codec", "eds:50", "--duration", duration, "--log", str(logs), "--quiet", *extra,
    )  # fmt: skip


@pytest.mark.integration
@pytest.mark.serial
def test_a_teleoperator_restarted_behind_a_2ms_link_rejoins_within_2s(tmp_path: Path, key: str) -> None:
    port = _free_port()
    relay = DelayRelay(("127.0.0.1", port), 0.002)
    try:
        to1 = _spawn("teleoperator", "--key-file", key, "--listen", f"127.0.0.1:{port}", "--quiet")
        wait_for(lambda: udp_bound(port), 60, "the teleoperator's socket")
        op = _operator(key, relay.addr, tmp_path / "op", "9")
        # Killed 3.5 s into the session (the new one must join after tick 3000).
        wait_for(lambda: ticks_logged(tmp_path / "op" / "operator.mcap") >= 3500, 60, "3500 ticks", poll=0.2)
        to1.kill()
        to1.wait()
        to2_logs = str(tmp_path / "to2")
        to2 = _spawn(
            "teleoperator", "--key-file", key, "--listen", f"127.0.0.1:{port}", "--log", to2_logs, "--quiet"
        )  # fmt: skip
        assert op.wait(timeout=60) in RAN, op.stderr.read() if op.stderr else ""
        assert to2.wait(timeout=60) in RAN, to2.stderr.read() if to2.stderr else ""
    finally:
        relay.close()
    o = json.loads((tmp_path / "op" / "operator.json").read_text())
    t = json.loads((tmp_path / "to2" / "teleoperator.json").read_text())
    assert o["rejoin"]["rejoins"] == 1 and o["completed"]
    assert t["joined_late"] and t["completed"] and t["first_tick"] > 3000
    # From the moment the new process could serve (its socket bound) to its joined session: the
    # operator's offers (every 250 ms), a retry, four welcomes, the start: well within 2 s.
    assert t["waited_for_session_s"] < 2.0, t["waited_for_session_s"]
    assert t["received"]["packets"] > 0
    for s in (o, t):  # eq. (5), up to float rounding in cumulative sums (teleop.offline.sim.ENERGY_TOLERANCE)
        assert s["passivity"]["min_margin"] >= -1e-9


@pytest.mark.integration
def test_a_relay_to_another_robot_with_the_same_key_never_starts_a_session(tmp_path: Path, key: str) -> None:
    """The operator names robot-a; what answers at the address is a relay to robot-b (same
    deployment key): robot-b cannot verify the hellos, and the operator fails with a clear line."""
    port = _free_port()
    b = _spawn(
        "teleoperator", "--key-file", key, "--listen", f"127.0.0.1:{port}", "--name", "robot-b",
        "--connect-timeout", "6", "--log", str(tmp_path / "b"),
    )  # fmt: skip
    relay = DelayRelay(("127.0.0.1", port), 0.0005)
    try:
        wait_for(lambda: udp_bound(port), 60, "robot-b's socket")
        op = _operator(
            key, relay.addr, tmp_path / "op", "3", "--robot-name", "robot-a", "--connect-timeout", "2"
        )
        _, err = op.communicate(timeout=30)
        _, b_err = b.communicate(timeout=30)
    finally:
        relay.close()
    assert op.returncode == 1 and "never answered" in err and "--name robot-a" in err, err
    assert len(err.strip().splitlines()) == 1  # one clear line, no traceback
    assert relay.forwarded > 0  # the hellos did reach robot-b
    assert b.returncode == 1 and "no operator said hello" in b_err, b_err
    assert not (tmp_path / "b" / "teleoperator.mcap").exists()


@pytest.mark.integration
def test_socket_activation_serves_on_the_socket_systemd_bound(tmp_path: Path, key: str) -> None:
    """As systemd starts it from teleop-teleoperator.socket: the socket is fd 3, LISTEN_PID is the
    process's own pid, and no --listen is needed."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    fd = sock.fileno()
    args = [*TELEOP, "teleoperator", "--key-file", key, "--quiet", "--log", str(tmp_path / "to")]
    # What systemd does between fork and exec: the socket to fd 3, LISTEN_PID = the pid that execs.
    activate = (
        "import os, sys; os.dup2(int(sys.argv[1]), 3); os.environ.update(LISTEN_FDS='1', "
        "LISTEN_PID=str(os.getpid())); os.execv(sys.argv[2], sys.argv[2:])"
    )
    to = subprocess.Popen(
        [sys.executable, "-c", activate, str(fd), *args],
        pass_fds=(fd,),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    sock.close()  # the child holds it now, as systemd would
    try:
        op = _operator(key, ("127.0.0.1", port), tmp_path / "op", "1")
        _, err = op.communicate(timeout=60)
        if op.returncode != 0:
            to.kill()
        assert op.returncode in RAN, (err, to.communicate(timeout=10))
        assert to.wait(timeout=60) in RAN, to.stderr.read() if to.stderr else ""
    finally:
        to.kill()
    t = json.loads((tmp_path / "to" / "teleoperator.json").read_text())
    assert t["local"] == f"127.0.0.1:{port}" and t["completed"]


@pytest.mark.integration  # a teleoperator process
def test_a_teleoperator_that_cannot_bind_says_so_in_one_line(key: str) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as squatter:
        squatter.bind(("127.0.0.1", 0))
        port = squatter.getsockname()[1]
        r = subprocess.run(
            [*TELEOP, "teleoperator", "--key-file", key, "--listen", f"127.0.0.1:{port}"],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert r.returncode == 1
    assert (
        r.stderr.strip()
        == f"teleop teleoperator: error: cannot bind UDP 127.0.0.1:{port}: Address already in use"
    )
    assert os.environ.get("LISTEN_PID") is None
