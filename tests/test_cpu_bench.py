"""``bench.cpu``: a run whose report lacks a process's figures stops the bench with the case named
and the run kept (it crashed with a TypeError minutes into a run, its evidence deleted)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

import bench
from bench import cpu


def test_a_report_without_a_process_stops_the_bench_and_keeps_the_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    class Fake:  # the empty loop alongside, and the session whose report lacks the operator
        pid = os.getpid()  # (the session's CPU sampler finds no process below it)
        returncode = 0

        def __init__(self, cmd: list[str], **kw: Any) -> None:
            if "--empty" in cmd:
                Path(cmd[cmd.index("--empty") + 1]).write_text(json.dumps({"period_error_us": {}}))
                return
            out = Path(cmd[cmd.index("--out") + 1])
            out.mkdir(parents=True)
            procs: dict[str, Any] = {"operator": None, "teleoperator": {"loop": {}}}
            rep = {"processes": procs, "summary_missing": ["operator"]}
            (out / "report.json").write_text(json.dumps(rep))

        def wait(self, timeout: float | None = None) -> int:
            return 0

        def communicate(self, timeout: float | None = None) -> tuple[str, str]:
            return "  operator     SUMMARY MISSING", ""

    monkeypatch.setattr("bench.cpu.subprocess.Popen", Fake)
    monkeypatch.setattr("bench.cpu.tempfile.mkdtemp", lambda prefix: str(tmp_path / f"{prefix}kept"))
    with pytest.raises(SystemExit) as e:
        cpu.run_case("none", 2, 1.0, tmp_path)
    msg = str(e.value)
    assert msg.startswith("teleop run none 2 DoF: the report has no figures of the operator ")
    assert "SUMMARY MISSING" in msg
    kept = tmp_path / "teleop-cpu-none-2-kept"
    assert f"kept in {kept}" in msg and (kept / "report.json").is_file()
    shutil.rmtree(kept)


@pytest.mark.integration  # git: processes
def test_the_commit_of_a_measured_tree_says_when_it_has_uncommitted_changes(tmp_path: Path) -> None:
    def git(*args: str) -> str:
        return subprocess.run(
            ["git", "-C", str(tmp_path), *args], check=True, capture_output=True, text=True
        ).stdout

    git("init", "-q")
    (tmp_path / "f.py").write_text("x = 1\n")
    git("add", "f.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "m")
    head = git("rev-parse", "HEAD").strip()
    (tmp_path / "new.txt").write_text("untracked: not the measured code\n")
    assert bench.commit(tmp_path) == head
    (tmp_path / "f.py").write_text("x = 2\n")
    assert bench.commit(tmp_path) == f"{head} with uncommitted changes"
    assert bench.commit(tmp_path / "no-such").startswith("unknown (")


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--duration", "nan"], "--duration must be a finite number, got 'nan'"),
        (["--duration", "1e999"], "--duration must be a finite number"),
        (["--duration", "0"], "--duration must be 1 to 600 s"),
        (["--tick-ticks", "-5"], "--tick-ticks must be an integer 100..1000000"),
        (["--tick-repeats", "1e3"], "--tick-repeats must be an integer 1..1000"),
    ],
)
def test_bad_arguments_are_refused_in_one_line_before_anything_runs(
    args: list[str], said: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A nan duration reached bench.floor and ended minutes later in a child's traceback."""
    monkeypatch.setattr("sys.argv", ["cpu.py", *args])
    monkeypatch.setattr("bench.cpu.run_floor", lambda *a: pytest.fail("ran the floor"))
    with pytest.raises(SystemExit) as e:
        cpu.main()
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert said in err and "Traceback" not in err


@pytest.mark.integration  # a child python and its own child
@pytest.mark.serial
def test_the_session_cpu_counts_every_process_below_from_the_start(tmp_path: Path) -> None:
    """SessionCpu sums the CPU of the processes below a pid (a grandchild too), from when the
    session starts, over the time from then to their exit."""
    import sys

    started = tmp_path / "started"
    burn = "import time; e = time.process_time() + 0.3\nwhile time.process_time() < e: pass"
    parent = (
        "import subprocess, sys, time, pathlib; e = time.process_time() + 0.2\n"
        "while time.process_time() < e: pass\n"  # before the start: not counted
        f"pathlib.Path({str(started)!r}).touch()\n"
        f"c = subprocess.Popen([sys.executable, '-c', {burn!r}])\n"
        "e = time.process_time() + 0.3\nwhile time.process_time() < e: pass\nc.wait()"
    )
    # The sampler watches the processes below ``top``, which only runs the parent's python.
    top = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import subprocess, sys; subprocess.run([sys.executable, '-c', sys.argv[1]])",
            parent,
        ]
    )
    sampler = cpu.SessionCpu(top.pid, started.exists, period=0.01)
    assert top.wait(timeout=60) == 0
    got = sampler.stop()
    assert got["processes"] == 2  # the parent and its child, not ``top`` above them
    assert 0.5 <= got["cpu_s"] <= 0.8, got  # 0.3 + 0.3 s after the start (the first 0.2 s is not)
    assert 0.0 < got["cpu_fraction_of_one_core"] <= 2.0


def test_the_hot_port_tick_is_timed_per_side_codec_and_dof() -> None:
    from bench import tick

    sides = tick.bench_sides(20, 1, codecs=("none", "eds:50"), dofs=(2, 64))
    assert [(s["codec"], s["dof"]) for s in sides] == [
        ("none", 2),
        ("eds:50", 2),
        ("none", 64),
        ("eds:50", 64),
    ]
    assert all(s["operator_us"] > 0 and s["teleoperator_us"] > 0 for s in sides)
    assert tick.SIDE_DOFS == (2, 6, 64) and {"none", "eds:50"} <= set(tick.SIDE_CODECS)


def test_instructions_are_counted_per_codec_at_2_6_and_64_dof() -> None:
    from bench import instructions, tick

    assert set(instructions.CASES) == {(c, d) for c in tick.SIDE_CODECS for d in (2, 6, 64)}
    assert cpu._case("pdp:1:64") == ("pdp:1", 64)
    with pytest.raises(Exception, match="CODEC:DOF"):
        cpu._case("none:65")
