"""The `teleop` command: contract of results.json, and clear errors for bad arguments."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from teleop.cli import main

TELEOP = [sys.executable, "-m", "teleop.cli"]


def test_sim_writes_contract(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["sim", "--codec", "ids:2", "--codec", "eds:2", "--duration", "1", "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads((tmp_path / "results.json").read_text())
    assert doc["dt"] == 0.001 and doc["duration"] == 1.0 and doc["delay_ms"] == 0
    assert [c["codec"] for c in doc["cases"]] == ["ids:2", "eds:2"]
    for c in doc["cases"]:
        for key, typ in [
            ("I", float),
            ("I_norm", float),
            ("compression", float),
            ("min_instant_compression", float),
            ("passive", bool),
            ("min_energy_margin", float),
        ]:
            assert isinstance(c[key], typ), key
    assert (tmp_path / "ids_2.png").stat().st_size > 10_000
    out = capsys.readouterr().out
    assert "ids:2" in out and "passive" in out


@pytest.mark.parametrize(
    "args,msg",
    [
        (["sim", "--codec", "mp3"], "unknown codec 'mp3'"),
        (["sim", "--delay", "-5"], "delay must be >= 0"),
        (["sim", "--duration", "abc"], "duration must be a number"),
        (["sim", "--dof", "0"], "DoF must be an integer 1..64"),
        (["sim", "--b", "0"], "wave impedance b must be > 0"),
    ],
)
@pytest.mark.integration  # the CLI as a process
def test_bad_arguments(args: list[str], msg: str) -> None:
    r = subprocess.run([sys.executable, "-m", "teleop.cli", *args], capture_output=True, text=True)
    assert r.returncode == 2
    assert msg in r.stderr


@pytest.mark.integration  # the CLI as a process
def test_sweep_draws_one_front_per_impairment_and_architecture(tmp_path: Path) -> None:
    """--netem and --passivity repeat: sweep.json holds one document per (impairment, architecture)
    and fronts.png one panel per impairment with both architectures."""
    out = tmp_path / "sw"
    r = subprocess.run(
        [*TELEOP, "sweep", "--codec", "none", "--codec", "pdp:1", "--netem", "", "--netem", "delay 20ms",
         "--passivity", "wave", "--passivity", "tdpa", "--duration", "1", "--jobs", "1", "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    doc = json.loads((out / "sweep.json").read_text())
    fronts = [(d["netem"]["forward"], d["passivity"]) for d in doc["fronts"]]
    assert fronts == [("", "wave"), ("", "tdpa"), ("delay 20ms", "wave"), ("delay 20ms", "tdpa")]
    for d in doc["fronts"]:
        assert [c["codec"] for c in d["cases"]] == ["none", "pdp:1"] and all(c["passive"] for c in d["cases"])
        assert any(c["pareto"] for c in d["cases"])
    assert (out / "fronts.png").stat().st_size > 10_000 and (out / "pareto.png").exists()


def test_run_says_how_each_process_ended_in_words() -> None:
    """Not a raw dict (``exit codes {'teleoperator': 1, 'operator': -15}``): one line a person reads."""
    from teleop.cli.run import exits

    assert exits({"teleoperator": 1, "operator": -15}) == "teleoperator exited 1, operator stopped by SIGTERM"
    ok = "teleoperator exited 0 (ok), operator never started"
    assert exits({"teleoperator": 0, "operator": None}) == ok


def test_progress_says_the_time_spent_and_the_time_left() -> None:
    """Sweeps and experiments showed ``[i/N]`` with no time left (issue 48)."""
    import io

    from teleop.cli.progress import Progress, duration_text

    now = [100.0]
    out = io.StringIO()
    p = Progress(4, out, "teleop experiment: ", clock=lambda: now[0])
    now[0] += 30.0
    p.step("none seed 0")
    assert out.getvalue() == "teleop experiment: 1/4 none seed 0  (30 s spent, about 1 min 30 s left)\n"
    now[0] += 90.0
    for _ in range(3):
        p.step("x")
    assert out.getvalue().splitlines()[-1].endswith("(2 min 00 s spent, done)")
    assert duration_text(3725) == "1 h 02 min"
