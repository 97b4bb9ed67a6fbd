"""The two-host recipe: operator and teleoperator in two network namespaces over a veth pair.

Needs root and iproute2; skipped with the reason otherwise.  The namespaces and addresses exist only
for the run and are checked to be gone afterwards.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from teleop.offline.logfile import read_log
from tests.ran import RAN

ROOT = Path(__file__).resolve().parents[1]
can_netns = os.geteuid() == 0 and shutil.which("ip") is not None
needs_netns = pytest.mark.skipif(
    not can_netns, reason="needs root and iproute2 (ip netns) to create test hosts"
)


def _netns() -> str:
    return subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=True).stdout


@needs_netns
@pytest.mark.integration
@pytest.mark.serial
def test_udp_between_two_namespaces(tmp_path: Path) -> None:
    teleop = str(Path(sys.executable).with_name("teleop"))
    env = {**os.environ, "TELEOP": teleop, "OUT": str(tmp_path), "DURATION": "2", "CODEC": "eds:50"}
    r = subprocess.run(
        ["bash", str(ROOT / "deploy/netns/udp.sh")], env=env, capture_output=True, text=True, timeout=120
    )
    assert r.returncode in RAN, r.stderr  # the script ends with the report's verdict
    rep = json.loads((tmp_path / "report.json").read_text())
    for d in ("forward", "backward"):
        _assert_eds50_count(rep, d, tmp_path / "logs")
        assert rep["link"][d]["loss"] == 0.0
    # The operator reached the teleoperator at its namespace address, not over loopback.
    op = json.loads((tmp_path / "logs" / "operator.json").read_text())
    to = json.loads((tmp_path / "logs" / "teleoperator.json").read_text())
    assert op["completed"] and op["params"]["codec"] == "eds:50"
    assert op["peer"] == "10.77.0.2:7000" and to["peer"].startswith("10.77.0.1:")
    assert "teleop-op-" not in _netns() and "teleop-to-" not in _netns()


@needs_netns
@pytest.mark.integration
@pytest.mark.serial
def test_zenoh_through_a_router_in_a_third_namespace(tmp_path: Path) -> None:
    teleop = str(Path(sys.executable).with_name("teleop"))
    env = {**os.environ, "TELEOP": teleop, "OUT": str(tmp_path), "DURATION": "2", "CODEC": "eds:50"}
    r = subprocess.run(
        ["bash", str(ROOT / "deploy/netns/zenoh.sh")], env=env, capture_output=True, text=True, timeout=120
    )
    assert r.returncode in RAN, r.stderr  # the script ends with the report's verdict
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["transport"] == "zenoh"
    for d in ("forward", "backward"):
        _assert_eds50_count(rep, d, tmp_path / "logs")
    op = json.loads((tmp_path / "logs" / "operator.json").read_text())
    assert op["completed"] and op["transport"] == "zenoh"
    left = _netns()
    assert "teleop-op-" not in left and "teleop-to-" not in left and "teleop-rt-" not in left


def _phase_moves(logs: Path) -> int:
    """Sends the teleoperator's eDS phase moves can add or drop: its send phase follows its playout
    target (PROTOCOL 3.5), which the host's jitter moves, one send at most per move (as
    tests/test_processes.py counts them)."""
    phase = read_log(logs / "teleoperator.mcap")[1]["send_phase"]
    moves = np.abs(np.diff(phase[phase >= 0]))
    return int(np.sum(moves[moves > 0] // 50 + 1))


def _assert_eds50_count(rep: dict[str, Any], d: str, logs: Path) -> None:
    """eds:50 for 2 s sends 40 payloads a direction, all received; a host stall that skipped ticks
    shifts the encoder's send ticks (it counts its calls), so then up to one fewer per 50 skipped;
    backward, each move of the send phase can add or drop one (a run sent 41)."""
    w = rep["wire"][d]
    skipped = rep["processes"]["operator" if d == "forward" else "teleoperator"]["loop"]["skipped"]
    moved = _phase_moves(logs) if d == "backward" else 0
    assert w["received_packets"] == w["packets"], (d, w)
    if skipped == 0 and moved == 0:
        assert w["packets"] == 40, (d, w["packets"])
    else:
        assert 40 - skipped // 50 - 1 - moved <= w["packets"] <= 40 + moved, (d, w["packets"], skipped, moved)
