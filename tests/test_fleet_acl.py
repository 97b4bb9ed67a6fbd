"""deploy/zenoh/fleet: the router's access control, as shipped, on a real router.

Strangers and wrong passwords cannot connect; a robot credential announces and is listed; an
operator or lister credential that declares a robot's token is refused by the router (never
listed); a lister lists; and a whole session by name runs through it with the robot and operator
credentials (so the rules allow everything a session needs)."""

from __future__ import annotations

import re
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from teleop.session import auth
from tests.ran import RAN
from tests.test_fleet_zenoh import ROOT, TELEOP, robots, stop
from tests.test_processes_zenoh import _free_tcp_port
from tests.waiting import tcp_listening, wait_for

pytestmark = pytest.mark.integration
FLEET = ROOT / "deploy/zenoh/fleet"
PASSWORDS = {"robot": "pw-robot-1", "operator": "pw-operator-2", "lister": "pw-lister-3"}


def _config(tmp: Path, role: str, endpoint: str, password: str | None = None) -> Path:
    """The shipped config of ``role`` for this test's router and password."""
    text = (FLEET / f"{role}.json5").read_text().replace("tcp/127.0.0.1:7447", endpoint)
    text = text.replace("PASSWORD", password or PASSWORDS[role])
    path = tmp / f"{role}-{password or 'ok'}.json5"
    path.write_text(text)
    path.chmod(0o600)
    return path


@pytest.fixture
def acl_router(tmp_path: Path) -> Iterator[str]:
    users = tmp_path / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in PASSWORDS.items()))
    users.chmod(0o600)
    port = _free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    text = (FLEET / "router-acl.json5").read_text().replace("/etc/teleop/zenoh-users.txt", str(users))
    assert str(users) in text
    config = tmp_path / "router.json5"
    config.write_text(text)
    proc = subprocess.Popen([*TELEOP, "router", "--listen", endpoint, "--config", str(config)])
    try:
        wait_for(lambda: tcp_listening(port), 60, "the router's listener")
        yield endpoint
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)


@pytest.fixture
def key(tmp_path: Path) -> Path:
    path = tmp_path / "k.key"
    auth.write_key_file(path, auth.generate_key())
    return path


def teleop_robots(endpoint: str, key: Path, config: Path | None) -> subprocess.CompletedProcess[str]:
    cfg = ["--zenoh-config", str(config)] if config else []
    return subprocess.run(
        [*TELEOP, "robots", "--zenoh-router", endpoint, "--key-file", str(key), *cfg],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_strangers_cannot_connect(acl_router: str, key: Path, tmp_path: Path) -> None:
    for config in (None, _config(tmp_path, "lister", acl_router, "wrong")):
        r = teleop_robots(acl_router, key, config)
        assert r.returncode == 2 and "cannot reach Zenoh router" in r.stderr, r.stderr
        assert r.stderr.count("\n") == 1


def test_only_a_robot_credential_announces_and_a_lister_lists(
    acl_router: str, key: Path, tmp_path: Path
) -> None:
    fleet = [
        robots(acl_router, key, "arm", 2, "--config", str(_config(tmp_path, "robot", acl_router))),
        robots(acl_router, key, "posing-op", 1, "--config", str(_config(tmp_path, "operator", acl_router))),
        robots(acl_router, key, "posing-lister", 1, "--config", str(_config(tmp_path, "lister", acl_router))),
    ]
    try:
        for who in ("lister", "operator"):
            r = teleop_robots(acl_router, key, _config(tmp_path, who, acl_router))
            assert r.returncode == 0, r.stderr
            assert "2 robots (2 trusted)" in r.stdout and "posing" not in r.stdout, r.stdout
            assert re.search(r"arm-0 +free", r.stdout) and re.search(r"arm-1 +free", r.stdout)
        # A robot credential may announce, not list: it sees no robot (its queries are refused).
        r = teleop_robots(acl_router, key, _config(tmp_path, "robot", acl_router))
        assert r.returncode == 0 and "0 robots" in r.stdout, r.stdout
    finally:
        for f in fleet:
            stop(f)


def test_a_session_by_name_runs_through_the_access_control(
    acl_router: str, key: Path, tmp_path: Path
) -> None:
    common = ["--transport", "zenoh", "--zenoh-mode", "client", "--zenoh-router", acl_router,
              "--key-file", str(key), "--no-rt"]  # fmt: skip
    to = subprocess.Popen(
        [*TELEOP, "teleoperator", *common, "--name", "arm", "--connect-timeout", "60",
         "--zenoh-config", str(_config(tmp_path, "robot", acl_router))],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        op = subprocess.run(
            [*TELEOP, "operator", *common, "--robot-name", "arm", "--duration", "2", "--codec", "eds:50",
             "--zenoh-config", str(_config(tmp_path, "operator", acl_router))],
            capture_output=True, text=True, timeout=90,
        )  # fmt: skip
        assert op.returncode in RAN, op.stderr
        said = op.stdout + op.stderr
        assert "found robot arm" in said and re.search(r"sent (\d+) packets, received \1\b", said), said
        assert to.wait(timeout=60) in RAN
    finally:
        if to.poll() is None:
            to.kill()
        to.wait(timeout=20)
