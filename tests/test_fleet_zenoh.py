"""Fleets through one router, real processes on loopback: 100 robots listed by ``teleop robots``,
a forged robot listed untrusted, a killed or frozen robot gone within 2 s, and an operator that
names a robot (no prefix, no address) starting a session while a racing one is refused."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from teleop.session import auth
from tests.ran import RAN
from tests.test_processes_zenoh import _free_tcp_port
from tests.waiting import tcp_listening, wait_for
from transport.fleet import Listed, list_robots
from transport.zenoh import make_config, open_session

pytestmark = pytest.mark.integration
TELEOP = [sys.executable, "-m", "teleop.cli"]
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def router() -> Iterator[str]:
    port = _free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = subprocess.Popen([*TELEOP, "router", "--listen", endpoint])
    try:
        wait_for(lambda: tcp_listening(port), 60, "the router's listener")
        yield endpoint
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)


@pytest.fixture
def key(tmp_path: Path) -> tuple[Path, bytes]:
    path = tmp_path / "k.key"
    psk = auth.generate_key()
    auth.write_key_file(path, psk)
    return path, psk


def robots(router: str, key_file: Path, prefix: str, n: int, *extra: str) -> subprocess.Popen[str]:
    """``n`` simulated robots (tests/fleet_robots.py) in one process, once all are announced."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.fleet_robots", router, str(key_file), prefix, str(n), *extra],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    return proc


def stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait(timeout=20)


def teleop_robots(router: str, key_file: Path) -> dict[str, Any]:
    r = subprocess.run(
        [*TELEOP, "robots", "--zenoh-router", router, "--key-file", str(key_file), "--json"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    out: dict[str, Any] = json.loads(r.stdout)
    return out


class Lister:
    """The test's own Zenoh client: listings without a process start each."""

    def __init__(self, router: str, psk: bytes) -> None:
        self.session = open_session(make_config("client", None, [router], None))
        self.psk = psk

    def names(self, trusted_only: bool = True) -> dict[str, Listed]:
        return {r.name: r for r in list_robots(self.session, self.psk) if r.trusted or not trusted_only}

    def close(self) -> None:
        self.session.close()


@pytest.mark.serial
def test_a_hundred_robots_are_listed_within_100_ms(router: str, key: tuple[Path, bytes]) -> None:
    fleet = robots(router, key[0], "sim", 100)
    try:
        took = []
        for _ in range(3):  # a loaded host: the best of three listings is the figure
            out = teleop_robots(router, key[0])
            rows = out["robots"]
            assert len(rows) == 100 and all(r["trusted"] and r["state"] == "free" for r in rows), rows[:3]
            assert sorted(r["name"] for r in rows) == sorted(f"sim-{i}" for i in range(100))
            took.append(out["seconds"])
        print(f"100 robots listed in {[round(t * 1e3, 1) for t in took]} ms; load {os.getloadavg()[0]:.1f}")
        assert min(took) <= 0.100, took
    finally:
        stop(fleet)


def test_a_router_admits_more_than_the_351_sessions_shared_memory_allowed(router: str) -> None:
    """One `teleop router` opened 351 plain client sessions and timed out every later one while
    Zenoh's shared-memory transport was on (its default); off (transport.zenoh), it admits them up to
    its max_sessions.  Opened one after another from one process, as bench.fleet counts them."""
    out = subprocess.run(
        [sys.executable, "-m", "bench.fleet", "--worker", "limit", "--router", router, "--max-pairs", "420"],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )  # fmt: skip
    got = json.loads(out.stdout)
    assert got["admitted"] == 420, got


def test_a_forged_robot_is_listed_untrusted(router: str, key: tuple[Path, bytes]) -> None:
    genuine = robots(router, key[0], "arm", 1)
    forged = robots(router, key[0], "fake", 1, "--stranger")
    try:
        out = {r["name"]: r for r in teleop_robots(router, key[0])["robots"]}
        assert out["arm-0"]["trusted"] and out["arm-0"]["state"] == "free"
        assert not out["fake-0"]["trusted"] and "bad tag" in out["fake-0"]["problem"], out["fake-0"]
        text = subprocess.run(
            [*TELEOP, "robots", "--zenoh-router", router, "--key-file", str(key[0])],
            capture_output=True,
            text=True,
            timeout=60,
        ).stdout
        assert "2 robots (1 trusted)" in text and "fake-0               UNTRUSTED: bad tag" in text, text
    finally:
        stop(genuine)
        stop(forged)


def _gone_within(lister: Lister, name: str, act: Any) -> float:
    wait_for(lambda: name in lister.names(), 30, f"{name} listed")
    t0 = time.monotonic()
    act()
    wait_for(lambda: name not in lister.names(trusted_only=False), 10, f"{name} gone", poll=0.02)
    return time.monotonic() - t0


@pytest.mark.serial
def test_a_killed_teleoperator_leaves_the_listing_within_2_s(router: str, key: tuple[Path, bytes]) -> None:
    lister = Lister(router, key[1])
    to = subprocess.Popen(
        [*TELEOP, "teleoperator", "--transport", "zenoh", "--zenoh-mode", "client", "--zenoh-router", router,
         "--name", "doomed", "--key-file", str(key[0]), "--no-rt", "--connect-timeout", "60"],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        took = _gone_within(lister, "doomed", to.kill)
        print(f"killed robot gone from the listing in {took * 1e3:.0f} ms")
        assert took <= 2.0
    finally:
        stop(to)
        lister.close()


@pytest.mark.serial
def test_a_frozen_robot_leaves_the_listing_within_its_lease(router: str, key: tuple[Path, bytes]) -> None:
    """SIGSTOP: no close, no FIN, no keep-alive, as with a pulled cable: the router's lease ends it."""
    lister = Lister(router, key[1])
    frozen = robots(router, key[0], "frozen", 1)
    try:
        took = _gone_within(lister, "frozen-0", lambda: frozen.send_signal(signal.SIGSTOP))
        print(f"frozen robot gone from the listing in {took * 1e3:.0f} ms (lease 1 s)")
        assert 0.5 <= took <= 2.0  # not before its lease had a chance to run out
    finally:
        frozen.send_signal(signal.SIGCONT)
        stop(frozen)
        lister.close()


def test_operators_naming_a_robot_race_and_one_session_starts(router: str, key: tuple[Path, bytes]) -> None:
    """No prefix and no robot address: each operator finds ``arm`` through the router.  Two start at
    once; the handshake lets exactly one in, the listing shows it busy, held by the winner."""
    k = str(key[0])
    lister = Lister(router, key[1])
    to = subprocess.Popen(
        [*TELEOP, "teleoperator", "--transport", "zenoh", "--zenoh-mode", "client", "--zenoh-router", router,
         "--name", "arm", "--key-file", k, "--no-rt", "--connect-timeout", "60", "--show-holder"],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        wait_for(lambda: "arm" in lister.names(), 30, "arm listed")

        def operator(session: int) -> subprocess.Popen[str]:
            return subprocess.Popen(
                [*TELEOP, "operator", "--transport", "zenoh", "--zenoh-mode", "client", "--zenoh-router",
                 router, "--robot-name", "arm", "--key-file", k, "--no-rt", "--duration", "3",
                 "--codec", "eds:50", "--session", str(session), "--quiet"],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            )  # fmt: skip

        def busy() -> Any:
            r = lister.names().get("arm")
            return (
                r is not None
                and r.description is not None
                and r.description.state == "busy"
                and r.description
            )

        ops = {s: operator(s) for s in (101, 102)}
        held = wait_for(busy, 30, "arm busy")
        codes = {s: p.wait(timeout=60) for s, p in ops.items()}
        winners = [s for s, c in codes.items() if c in RAN]
        errs = {s: p.stderr.read() if p.stderr else "" for s, p in ops.items()}
        assert len(winners) == 1, (codes, errs)
        assert held.holder == winners[0]
        (loser,) = set(ops) - set(winners)
        assert "busy" in errs[loser] or "start" in errs[loser], errs[loser]
        assert to.wait(timeout=60) in RAN
    finally:
        stop(to)
        lister.close()


@pytest.mark.parametrize("robot", ["absent", "fake-0"])
def test_an_operator_never_takes_an_untrusted_or_absent_robot(
    router: str, key: tuple[Path, bytes], robot: str
) -> None:
    forged = robots(router, key[0], "fake", 1, "--stranger")
    try:
        r = subprocess.run(
            [*TELEOP, "operator", "--transport", "zenoh", "--zenoh-mode", "client", "--zenoh-router", router,
             "--robot-name", robot, "--key-file", str(key[0]), "--no-rt", "--connect-timeout", "1"],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    finally:
        stop(forged)
    said = {"absent": "not announced", "fake-0": "announced but not trusted (bad tag"}[robot]
    assert r.returncode == 1 and f"robot {robot} not found through Zenoh in 1 s: {said}" in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1


def test_a_second_robot_of_one_name_does_not_start(router: str, key: tuple[Path, bytes]) -> None:
    first = robots(router, key[0], "twin", 1)
    try:
        r = subprocess.run(
            [*TELEOP, "teleoperator", "--transport", "zenoh", "--zenoh-mode", "client",
             "--zenoh-router", router, "--name", "twin-0", "--key-file", str(key[0]), "--no-rt",
             "--connect-timeout", "5"],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    finally:
        stop(first)
    assert r.returncode == 1 and "a robot named twin-0 is already announced here" in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1
