"""bench.instructions: how it reads cachegrind, what it refuses, and one real count."""

from __future__ import annotations

import os
import shutil
import stat
from pathlib import Path

import pytest

from bench import instructions


def _fake_valgrind(tmp_path: Path, stderr: str, code: int = 0) -> dict[str, str]:
    """A ``valgrind`` on PATH that prints ``stderr`` and exits ``code`` (the environment to use)."""
    exe = tmp_path / "valgrind"
    exe.write_text(f"#!/bin/sh\ncat >&2 <<'EOF'\n{stderr}\nEOF\nexit {code}\n")
    exe.chmod(exe.stat().st_mode | stat.S_IEXEC)
    return {"PATH": f"{tmp_path}{os.pathsep}{os.environ['PATH']}"}


@pytest.mark.integration  # a fake valgrind: a shell script run as a process
def test_reads_the_i_refs_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for k, v in _fake_valgrind(tmp_path, "==7== \n==7== I   refs:      1,806,733,016\n").items():
        monkeypatch.setenv(k, v)
    assert instructions.instructions("none", 2, 100, None) == 1_806_733_016


@pytest.mark.integration  # a fake valgrind: a shell script run as a process
def test_a_failed_run_says_which_and_why(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for k, v in _fake_valgrind(tmp_path, "Traceback ...\nValueError: bad codec", code=1).items():
        monkeypatch.setenv(k, v)
    with pytest.raises(
        instructions.BenchError, match=r"cachegrind of none at 2 DoF, 100 ticks failed.*bad codec"
    ):
        instructions.instructions("none", 2, 100, None)


@pytest.mark.parametrize(
    "argv, says",
    [
        (["--from", "abc"], "whole number of ticks"),
        (["--to", "1e9"], "whole number of ticks"),
        (["--to", "70000"], "must be in 0..60000"),
        (["--from", "-1"], "must be in 0..60000"),
        (["--from", "500", "--to", "550"], "at least 100 ticks after"),
        (["--reference", "/"], "not a checkout of this project"),
    ],
)
def test_refuses_bad_arguments_in_one_line(
    argv: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as e:
        instructions.main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert says in err


@pytest.mark.integration  # valgrind
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind is not installed here")
def test_a_real_count_is_the_same_twice() -> None:
    """Two counts of the same code give the same figure to a few instructions a tick: the yardstick
    noise cannot move (the docs' claim)."""
    a = instructions.per_tick("eds:50", 2, 100, 300, None)["per_tick"]
    b = instructions.per_tick("eds:50", 2, 100, 300, None)["per_tick"]
    assert 20_000 < a < 2_000_000
    assert abs(a - b) < 0.01 * a


def test_out_must_be_a_regular_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A folder, a FIFO (writing would block) or a link (never followed) as --out: one line, before
    any counting."""
    fifo, link = tmp_path / "fifo", tmp_path / "link"
    os.mkfifo(fifo)
    link.symlink_to(tmp_path / "elsewhere.json")
    for out in (tmp_path, fifo, link):
        with pytest.raises(SystemExit) as e:
            instructions.main(["--out", str(out)])
        assert e.value.code == 2
        assert "not a regular file" in capsys.readouterr().err
    assert not (tmp_path / "elsewhere.json").exists()
