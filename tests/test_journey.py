"""A new user's first hour, scripted (issue 48's "done when"), in the order a person meets it, with
the installed ``teleop`` command in a folder of their own and nothing on PYTHONPATH:

1. a key, then a robot started alone, which waits (past the old 10 s give-up) and says where;
   then the operator, typed later; both end with a verdict line;
2. ``teleop run`` twice into one folder: ``report.json`` is the newest, each report kept by session;
3. a netem delay without a unit: refused in one line naming the units, before any session;
4. a poor session: a verdict line saying why, and exit status 3;
5. ``--print-config`` fed back through ``--config``: the same session;
6. a device plug-in in the current folder.

Every command's output is free of tracebacks, and each ends as the docs say.  It is one test on
purpose: a journey is the sum of its steps on one machine, in one folder."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from teleop.session.verdict import POOR_EXIT

from .test_first_hour import PLUGIN, _lines
from .waiting import wait_for

#: The teleoperator's old default gave up on its operator after this long; the journey waits past it.
OLD_GIVE_UP_S = 10.0


def _teleop(cwd: Path, *argv: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    r = subprocess.run([TELEOP, *argv], capture_output=True, text=True, timeout=timeout, cwd=cwd, env=ENV)
    assert "Traceback" not in r.stdout + r.stderr, r.stdout + r.stderr
    return r


TELEOP = str(Path(sys.executable).with_name("teleop"))
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def _verdict(text: str, who: str) -> str:
    last = text.strip().splitlines()[-1]
    assert last.startswith(f"teleop {who}: verdict: "), text
    return last


@pytest.mark.integration
def test_a_new_users_first_hour_meets_no_surprise(tmp_path: Path) -> None:
    home = tmp_path
    # 1. A key, a robot alone, then its operator once the old give-up is long past.
    assert _teleop(home, "keygen", "lab.key").returncode == 0
    robot = subprocess.Popen(
        [TELEOP, "teleoperator", "--key-file", "lab.key", "--listen", "127.0.0.1:0", "--name", "arm-1"],
        stderr=subprocess.PIPE, text=True, cwd=home, env=ENV,
    )  # fmt: skip
    try:
        lines = _lines(robot)
        started = time.monotonic()
        wait_for(lambda: lines, 60, "the robot's waiting line")
        assert "robot 'arm-1' on udp 127.0.0.1:" in lines[0] and "until stopped (Ctrl-C)" in lines[0]
        port = lines[0].split("on udp 127.0.0.1:")[1].split(":")[0]
        # The person walks to the other terminal: the wait is the scenario (no event to wait for).
        time.sleep(max(0.0, OLD_GIVE_UP_S + 1 - (time.monotonic() - started)))
        assert robot.poll() is None, lines
        op = _teleop(
            home, "operator", "--key-file", "lab.key", "--peer", f"127.0.0.1:{port}",
            "--robot-name", "arm-1", "--duration", "1", "--log", "op-logs",
        )  # fmt: skip
        assert op.returncode in (0, POOR_EXIT), op.stderr
        _verdict(op.stderr, "operator")
        wait_for(lambda: any("verdict:" in line for line in lines), 30, "the robot's verdict")
    finally:
        if robot.poll() is None:
            robot.send_signal(signal.SIGINT)
        robot.wait(timeout=30)
    assert any(line.startswith("teleop teleoperator: verdict: ") for line in lines), lines

    # 2. Two runs into one folder: report.json is the second's, both kept under their sessions.
    sessions = []
    for _ in range(2):
        r = _teleop(home, "run", "--duration", "1", "--out", "runs", "--no-plots", "--no-live")
        assert r.returncode in (0, POOR_EXIT), r.stdout + r.stderr
        _verdict(r.stdout, "run")
        sessions.append(json.loads((home / "runs" / "report.json").read_text())["session"])
    assert sessions[0] != sessions[1]
    assert {p.name for p in (home / "runs").glob("report-*.json")} == {f"report-{s}.json" for s in sessions}

    # 3. A delay without a unit: tc reads microseconds, a person meant milliseconds.
    r = _teleop(home, "run", "--netem", "delay 50", "--out", "unitless")
    assert r.returncode == 2 and not (home / "unitless").exists()
    first = r.stderr.strip().splitlines()[0]  # then the grammar, as a reminder
    assert first.startswith("teleop: error: argument --netem:"), r.stderr
    assert "a time needs its unit (s, ms, us or ns)" in first, r.stderr

    # 4. A poor session: bursts of loss that outlast the link timeout.
    r = _teleop(
        home, "run", "--duration", "2", "--codec", "none", "--netem", "loss gemodel 1% 1%",
        "--out", "poor", "--no-plots", "--no-live",
    )  # fmt: skip
    assert r.returncode == POOR_EXIT, r.stdout + r.stderr
    assert "the link was lost" in _verdict(r.stdout, "run")

    # 5. The settings in effect as a file, fed back: the same session.
    r = _teleop(home, "run", "--codec", "ids:2", "--duration", "1", "--no-plots", "--print-config")
    assert r.returncode == 0 and 'codec = "ids:2"' in r.stdout, r.stdout
    (home / "session.toml").write_text(r.stdout)
    r = _teleop(home, "run", "--config", "session.toml", "--out", "again", "--no-live")
    assert r.returncode in (0, POOR_EXIT), r.stdout + r.stderr
    rep = json.loads((home / "again" / "report.json").read_text())
    assert rep["codec"] == "ids:2" and rep["duration_s"] == 1.0
    assert not list((home / "again").glob("*.png"))  # --no-plots came from the file

    # 6. A device of the lab's own, in the folder it works in.
    (home / "labdevices.py").write_text(PLUGIN)
    r = _teleop(home, "sim", "--robot", "labdevices:Arm", "--duration", "0.2", "--out", "plug")
    assert r.returncode == 0, r.stderr
    assert (home / "plug" / "results.json").is_file()
