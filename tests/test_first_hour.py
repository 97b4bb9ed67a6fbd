"""What a new user meets in the first hour (issue 48), each as a test: a robot that waits for its
operator and says where, a Ctrl-C that is a person's choice, not an error."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from .waiting import wait_for

TELEOP = [sys.executable, "-m", "teleop.cli"]


def _lines(p: subprocess.Popen[str]) -> list[str]:
    """``p``'s stderr lines as they come, read by a thread (the list grows while the test waits)."""
    got: list[str] = []

    def read() -> None:
        assert p.stderr is not None
        got.extend(iter(p.stderr.readline, ""))

    threading.Thread(target=read, daemon=True).start()
    return got


@pytest.mark.integration
def test_a_robot_waits_for_its_operator_until_stopped_saying_where(tmp_path: Path) -> None:
    p = subprocess.Popen(
        [*TELEOP, "teleoperator", "--insecure", "--listen", "127.0.0.1:0", "--name", "arm-2"],
        stderr=subprocess.PIPE, text=True, cwd=tmp_path,
    )  # fmt: skip
    try:
        lines = _lines(p)
        wait_for(lambda: lines, 60, "the waiting line")
        assert lines[0].startswith("teleop teleoperator: robot 'arm-2' on udp 127.0.0.1:")
        assert "waiting for an operator until stopped (Ctrl-C)" in lines[0]
        assert "--robot-name arm-2" in lines[0]
        assert p.poll() is None  # it waits; the old default gave up after 10 s
        p.send_signal(signal.SIGINT)
        assert p.wait(timeout=10) == 130
        wait_for(lambda: len(lines) >= 2, 10, "the last line")
        said = "teleop teleoperator: stopped while waiting for an operator; no session ran"
        assert lines[1].strip() == said
    finally:
        p.kill()


@pytest.mark.integration
def test_a_robot_told_to_wait_a_while_gives_up_in_one_line(tmp_path: Path) -> None:
    r = subprocess.run(
        [*TELEOP, "teleoperator", "--insecure", "--listen", "127.0.0.1:0", "--wait", "0.5"],
        capture_output=True, text=True, timeout=60, cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 2 and "waiting for an operator for at most 0.5 s" in lines[0]
    assert lines[1].startswith("teleop teleoperator: error: no operator said hello within 0.5 s")


PLUGIN = '''
import numpy as np

class Arm:
    role = "robot"
    hardware = False  # a model: teleop sim may build it

    def __init__(self, dof, dt, arg):
        self.z = np.zeros(dof)

    def affine(self, now):
        return np.zeros(len(self.z)), self.z

    def advance(self, now, v, f):
        pass
'''


@pytest.mark.integration
def test_a_device_plug_in_in_the_current_folder_is_found(tmp_path: Path) -> None:
    """The installed ``teleop`` command (not ``python -m``, which has the folder already), run
    where the plug-in lies, with no PYTHONPATH."""
    (tmp_path / "mydevices_first_hour.py").write_text(PLUGIN)
    teleop = Path(sys.executable).with_name("teleop")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run(
        [str(teleop), "sim", "--robot", "mydevices_first_hour:Arm", "--duration", "0.2", "--out", "o"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path, env=env,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "o" / "results.json").is_file()
