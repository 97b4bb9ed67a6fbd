"""Issue 35 over real UDP: two processes through a relay on 127.0.0.1 that delays every datagram
800 ms each way (a round trip the fixed 300 ms start lead could not serve; shorter ones run in
virtual time).  A session starts and completes there, and a teleoperator restarted there rejoins.

The relay is ``tests.test_restart_real.DelayRelay`` (a thread of the test with a bounded life).
Nothing sleeps for a fixed time: the tests wait for the files and exits they need.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from tests.ran import RAN
from tests.test_processes import _free_port, _spawn
from tests.test_restart_real import DelayRelay, _operator
from tests.waiting import wait_for

DELAYS_MS = (130, 300, 800)


def _wait_for(path: Path, timeout_s: float) -> None:
    wait_for(path.exists, timeout_s, f"{path} to appear")


def _robot(key: str, port: int, log: Path) -> subprocess.Popen[str]:
    """A teleoperator on ``port`` logging to ``log``, waiting up to 30 s for its operator."""
    return _spawn(
        "teleoperator", "--key-file", key, "--listen", f"127.0.0.1:{port}", "--quiet",
        "--connect-timeout", "30", "--log", str(log),
    )  # fmt: skip


@pytest.mark.integration
# The longest only, as for the rejoin below: a start at 0.26, 0.3, 0.6, 1.6 and 2 s round trip runs in
# virtual time (tests/test_endpoint_robust.py); the real runner is shown once, where it is longest.
@pytest.mark.parametrize("delay_ms", DELAYS_MS[-1:])
def test_a_session_starts_and_completes_behind_a_long_delay(tmp_path: Path, key: str, delay_ms: int) -> None:
    port = _free_port()
    relay = DelayRelay(("127.0.0.1", port), delay_ms / 1e3)
    try:
        to = _robot(key, port, tmp_path / "to")
        op = _operator(key, relay.addr, tmp_path / "op", "2", "--connect-timeout", "30")
        _, op_err = op.communicate(timeout=90)
        _, to_err = to.communicate(timeout=30)
    finally:
        relay.close()
    assert op.returncode in RAN, op_err
    assert to.returncode in RAN, to_err
    o = json.loads((tmp_path / "op" / "operator.json").read_text())
    t = json.loads((tmp_path / "to" / "teleoperator.json").read_text())
    assert o["completed"] and t["completed"] and not t["joined_late"]
    assert o["handshake_rtt_us"] >= 2 * delay_ms * 1e3
    assert o["received"]["packets"] > 0 and t["received"]["packets"] > 0


@pytest.mark.integration
# The longest only: a rejoin at 0.26, 0.3, 1.6 and 2 s round trip runs in virtual time
# (tests/test_endpoint_robust.py); each real case here costs 12-25 s of the suite.
@pytest.mark.parametrize("delay_ms", DELAYS_MS[-1:])
def test_a_restarted_robot_rejoins_behind_a_long_delay(tmp_path: Path, key: str, delay_ms: int) -> None:
    port = _free_port()
    relay = DelayRelay(("127.0.0.1", port), delay_ms / 1e3, lifetime_s=120.0)
    # TO1 dies before its tick 0: the operator's link, never heard from, is lost 2 round trips after
    # it; then the restart's import, a cookie round trip, four welcomes and the start.
    duration = 8 + 8 * delay_ms / 1e3
    try:
        to1 = _robot(key, port, tmp_path / "to1")
        op = _operator(key, relay.addr, tmp_path / "op", f"{duration:g}", "--connect-timeout", "30")
        _wait_for(tmp_path / "to1" / "teleoperator.mcap", 60.0)  # its session started
        _wait_for(tmp_path / "op" / "operator.mcap", 60.0)
        to1.kill()
        to1.wait()
        to2 = _robot(key, port, tmp_path / "to2")
        _, op_err = op.communicate(timeout=120)
        _, to2_err = to2.communicate(timeout=60)
    finally:
        relay.close()
    assert op.returncode in RAN, op_err
    assert to2.returncode in RAN, to2_err
    o = json.loads((tmp_path / "op" / "operator.json").read_text())
    t = json.loads((tmp_path / "to2" / "teleoperator.json").read_text())
    assert o["rejoin"]["rejoins"] == 1 and o["completed"]
    assert t["joined_late"] and t["completed"] and t["received"]["packets"] > 0
