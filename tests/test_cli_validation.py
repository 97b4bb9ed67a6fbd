"""Every bad argument of `teleop` is one line, ``teleop: error: ...``, exit status 2, before any session.

Most cases run ``main`` in-process with the session entry points replaced by a tripwire, so a check
that came too late would fail loudly instead of starting a session.  Only loopback addresses and the
reserved ``.invalid`` name are used.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

import shell.process
import teleop.cli.run
import teleop.offline.sim
from teleop import limits
from teleop.cli import build_parser, main
from teleop.cli.settings import private_dir

BAD_HOST = "no-such-host.invalid"
PEER = ["--peer", "127.0.0.1:9", "--connect-timeout", "1"]
LISTEN = ["--listen", "127.0.0.1:0", "--connect-timeout", "1"]


class SessionStarted(AssertionError):
    pass


@pytest.fixture
def no_session(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any session (simulated, a process, or two child processes) trips the test."""

    def trip(*args: Any, **kwargs: Any) -> Any:
        raise SessionStarted("a session started despite a bad argument")

    monkeypatch.setattr(shell.process, "run_endpoint", trip)
    monkeypatch.setattr(teleop.offline.sim, "run_set", trip)
    monkeypatch.setattr(teleop.cli.run, "_spawn", trip)


def _error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``teleop ARGV`` in-process; assert exit status 2 and a one-line error; return stderr."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2, err
    assert "Traceback" not in err
    assert err.startswith("teleop: error: ") and len(err.strip().splitlines()) == 1, err
    return err


def _not_a_folder(tmp_path: Path) -> Path:
    """A path under a regular file: cannot be created whoever runs the test (root included)."""
    (tmp_path / "afile").write_text("x")
    return tmp_path / "afile" / "sub"


TRACE = "trace /nonexistent/trace: No such file or directory"
DURATION = "duration must be 0.1 to"
RUN_DURATION = "duration must be 0 (until stopped) or 0.1 to 604800 s"
MAX_SEED, MAX_SESSION = limits.MAX_SEED, limits.MAX_SESSION

CASES: list[tuple[list[str], str]] = [
    # a missing trace file, in every command that takes impairments and every impairment option
    *[
        ([cmd, *extra, opt, "trace /nonexistent/trace"], TRACE)
        for cmd, extra in (("sim", []), ("run", []), ("operator", PEER))
        for opt in ("--netem", "--netem-forward", "--netem-backward")
    ],
    # seeds and session ids: what the wire carries
    (["sim", "--seed", "-1"], f"seed must be an integer 0..{MAX_SEED}, got '-1'"),
    (["run", "--seed", str(MAX_SEED + 1)], f"seed must be an integer 0..{MAX_SEED}"),
    (["operator", *PEER, "--seed", "1e30"], f"seed must be an integer 0..{MAX_SEED}"),
    (
        ["operator", *PEER, "--session", "-5"],
        f"session must be an integer 0..{MAX_SESSION} (0: a random one)",
    ),
    (["operator", *PEER, "--session", str(MAX_SESSION + 1)], f"session must be an integer 0..{MAX_SESSION}"),
    # durations: finite; teleop sim keeps every tick, so its records must fit (at the DoF in force)
    # and it must end; a real session may run until stopped (0) or up to a week
    (["sim", "--duration", "1e12"], f"{DURATION} 5592.4 s at 1 DoF"),
    (["sim", "--duration", "1e-9"], DURATION),
    (["sim", "--duration", "0"], DURATION),
    (["sim", "--scenario", "protocol", "--duration", "1e12"], "s at 2 DoF"),
    (["sim", "--dof", "64", "--duration", "1000"], f"{DURATION} 486.296 s at 64 DoF"),
    (["sim", "--duration", "inf"], "duration must be a finite number, got 'inf'"),
    (["sim", "--duration", "nan"], "duration must be a finite number, got 'nan'"),
    (["run", "--duration", "1e12"], RUN_DURATION),
    (["run", "--duration", "1e-9"], RUN_DURATION),
    (["run", "--duration", "-1"], "duration must be >= 0, got '-1'"),
    (["operator", *PEER, "--duration", "1e12"], RUN_DURATION),
    (["operator", *PEER, "--duration=-inf"], "duration must be a finite number"),
    (["teleoperator", *LISTEN, "--duration", "1e12"], RUN_DURATION),
    (["teleoperator", *LISTEN, "--scenario", "protocol", "--duration", "1e12"], RUN_DURATION),
    (["teleoperator", *LISTEN, "--duration", "1e-9"], RUN_DURATION),
    # model and watchdog ranges
    (["sim", "--link-timeout", "0.5"], "link timeout must be 1 to 10000 ms, got '0.5'"),
    (["run", "--link-timeout", "1e6"], "link timeout must be 1 to 10000 ms"),
    (["operator", *PEER, "--link-timeout", "nan"], "link timeout must be a finite number"),
    (["sim", "--b", "1e9"], "wave impedance b must be > 0 and <= 1e+06 N s/m, got '1e9'"),
    (["run", "--range", "1e7"], "range must be > 0 and <= 1e+06 sqrt(W), got '1e7'"),
    (["teleoperator", *LISTEN, "--b", "inf"], "wave impedance b must be a finite number"),
    # process options
    (["run", "--port", "70000"], "port must be an integer 0..65535 (0: a free one), got '70000'"),
    (["run", "--port", "-1"], "port must be an integer 0..65535"),
    (["run", "--port", "x"], "port must be an integer 0..65535"),
    (["operator", *PEER, "--grace-us", "5000"], "grace must be >= 0 and <= 900 us (within the 1 ms tick)"),
    (["teleoperator", *LISTEN, "--grace-us", "1e300"], "grace must be >= 0 and <= 900 us"),
    (["operator", *PEER[:2], "--connect-timeout", "1e300"], "connect timeout must be > 0 and <= 86400 s"),
    (["run", "--connect-timeout", "inf"], "connect timeout must be a finite number"),
    # host names are resolved when parsed
    (["operator", "--peer", f"{BAD_HOST}:7000"], f"cannot resolve host '{BAD_HOST}' to an IPv4 address"),
    (["operator", *PEER, "--listen", f"{BAD_HOST}:0"], f"cannot resolve host '{BAD_HOST}'"),
    (["teleoperator", "--listen", f"{BAD_HOST}:7000"], f"cannot resolve host '{BAD_HOST}'"),
    # the messages the older tests rely on
    (["run", "--codec", "zz"], "unknown codec 'zz'"),
    (["operator", "--peer", "nohostport"], "--peer must be HOST:PORT"),
    (["teleoperator", "--listen", "127.0.0.1:99999"], "port must be an integer 0..65535"),
    (["sim", "--dof", "65"], "DoF must be an integer 1..64, got '65'"),
    # the robot name, the robot's own limits and conformance's bounds
    (["teleoperator", *LISTEN, "--name", "bad/name"], "a robot name is 1 to 64 of the characters"),
    (["operator", *PEER, "--robot-name", "x" * 65], "a robot name is 1 to 64 of the characters"),
    (["teleoperator", *LISTEN, "--max-range", "nan"], "max range must be a finite number"),
    (["teleoperator", *LISTEN, "--insecure", "--min-b", "30"], "--min-b 30 exceeds --max-b 20"),
    (["teleoperator", *LISTEN, "--insecure", "--b", "0.5", "--min-b", "1"], "--b 0.5 is below --min-b 1"),
    (["teleoperator", *LISTEN, "--insecure", "--range", "3", "--max-range", "2"], "--range 3 is beyond"),
    (
        ["teleoperator", *LISTEN, "--insecure", "--allow-passivity", "wave,magic"],
        "--allow-passivity 'wave,magic': must name some of wave, tdpa",
    ),
    (["teleoperator", *LISTEN, "--insecure", "--allow-on-loss", ""], "--allow-on-loss '': must name some of"),
    (["teleoperator", *LISTEN, "--max-link-timeout", "20000"], "max link timeout must be 1 to 10000 ms"),
    (["teleoperator", *LISTEN, "--max-backward-queue", "0"], "max backward queue must be an integer 1.."),
    (["teleoperator", *LISTEN, "--max-backward-hold", "-1"], "max backward hold must be"),
    (["teleoperator", *LISTEN, "--max-velocity", "inf"], "max velocity must be a finite number"),
    (["teleoperator", *LISTEN, "--max-force", "-1"], "max force must be > 0"),
    (["teleoperator", *LISTEN, "--max-playout", "900"], "max playout must be >= 0 and <= 500 ms"),
    (
        ["conformance", "teleoperator", "--insecure", "--peer", "127.0.0.1:9", "--duration", "-5"],
        "duration must be 0.5 to 60 s",
    ),
    (["conformance", "operator", "--insecure", "--timeout", "nan"], "timeout must be a finite number"),
]


@pytest.mark.parametrize("argv,msg", CASES, ids=[" ".join(a) for a, _ in CASES])
@pytest.mark.usefixtures("no_session")
def test_bad_argument_is_one_clear_line(
    argv: list[str], msg: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert msg in _error(argv, capsys)


@pytest.mark.parametrize(
    "cmd,extra,option",
    [
        ("sim", [], "--out"),
        ("run", [], "--out"),
        ("operator", PEER, "--log"),
        ("teleoperator", LISTEN, "--log"),
    ],
)
@pytest.mark.usefixtures("no_session")
def test_unwritable_folder(
    cmd: str, extra: list[str], option: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = _not_a_folder(tmp_path)
    err = _error([cmd, *extra, option, str(bad)], capsys)
    assert (
        f"{option} {bad}: cannot create or write to this folder: {bad.parent} is a file, not a folder" in err
    )


@pytest.mark.usefixtures("no_session")
def test_unwritable_report_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    for name in ("operator.mcap", "teleoperator.mcap"):
        (logs / name).write_text("")
    bad = _not_a_folder(tmp_path)
    err = _error(["report", str(logs), "--out", str(bad)], capsys)
    assert f"--out {bad}: cannot create or write to this folder: {bad.parent} is a file" in err
    # the folder itself a file
    err = _error(["report", str(logs), "--out", str(bad.parent)], capsys)
    assert f"--out {bad.parent}: cannot create or write to this folder: {bad.parent} is a file" in err


def test_private_dir_creates_and_leaves_nothing(tmp_path: Path) -> None:
    d = private_dir(tmp_path / "a" / "b", "--out")
    assert d.is_dir() and list(d.iterdir()) == []


def test_good_values_at_the_bounds() -> None:
    p = build_parser()
    a = p.parse_args(["operator", "--peer", "localhost:7000", "--listen", "localhost:0", "--session", "0"])
    assert a.peer == ("127.0.0.1", 7000) and a.listen == ("127.0.0.1", 0) and a.session == 0
    a = p.parse_args(["teleoperator", "--listen", "localhost:7000", "--grace-us", "900"])
    assert a.listen == ("127.0.0.1", 7000) and a.grace_us == 900.0
    a = p.parse_args(["sim", "--seed", str(MAX_SEED), "--link-timeout", "1", "--b", "1e6", "--range", "1e6"])
    assert a.seed == MAX_SEED and a.link_timeout == 1.0 and a.b == 1e6
    a = p.parse_args(["run", "--port", "65535", "--link-timeout", "10000", "--netem-forward", ""])
    assert a.port == 65535 and a.link_timeout == 10000.0 and a.netem_forward == ""
    a = p.parse_args(["operator", "--session", str(MAX_SESSION), "--peer", "127.0.0.1:7000"])
    assert a.session == MAX_SESSION


def test_trace_file_is_read_when_parsed(tmp_path: Path) -> None:
    trace = tmp_path / "trace"
    trace.write_text("1\n2\n")
    a = build_parser().parse_args(["sim", "--netem-forward", f"trace {trace}"])
    assert a.netem_forward == f"trace {trace}"


@pytest.mark.parametrize(
    "cmd,default",
    [
        ("sim", "default step"),
        ("run", "default protocol"),
        ("operator", "default protocol"),
        ("teleoperator", "default whatever the operator proposes"),
    ],
)
def test_scenario_help_states_the_real_default(
    cmd: str, default: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as e:
        main([cmd, "--help"])
    assert e.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    assert f"step (Section V) or protocol (Section VI); {default}" in out
    real = build_parser().parse_args([cmd]).scenario
    assert real == (None if cmd == "teleoperator" else default.split()[-1])


@pytest.mark.parametrize("cmd", ["router", "report"])
def test_other_helps(cmd: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main([cmd, "--help"])
    assert e.value.code == 0 and f"usage: teleop {cmd}" in capsys.readouterr().out


@pytest.mark.parametrize(
    "args,msg",
    [
        (["--help"], None),
        (["sim", "--netem", "trace /nonexistent/trace"], TRACE),
        (["operator", "--peer", f"{BAD_HOST}:7000"], f"cannot resolve host '{BAD_HOST}'"),
        (["sim", "--duration", "1e12"], DURATION),
    ],
)
@pytest.mark.integration  # the CLI as a process
def test_as_a_process(args: list[str], msg: str | None) -> None:
    """`python -m teleop.cli`: the same one line and no traceback in a real process."""
    r = subprocess.run(
        [sys.executable, "-m", "teleop.cli", *args], capture_output=True, text=True, timeout=60
    )
    assert "Traceback" not in r.stderr
    if msg is None:
        assert r.returncode == 0 and "usage: teleop" in r.stdout and "COMMAND" in r.stdout
    else:
        assert r.returncode == 2 and r.stderr.startswith("teleop: error: ") and msg in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "argv",
    [
        ["sim", "--duration", "1"],
        ["run", "--duration", "1"],
        ["operator", *PEER, "--insecure"],  # a key is required (tests/test_cli_auth.py)
        ["teleoperator", *LISTEN, "--insecure"],
    ],
)
@pytest.mark.usefixtures("no_session")
def test_the_tripwire_sees_a_session(argv: list[str], tmp_path: Path) -> None:
    """With good arguments each command reaches its session: so the cases above stopped before it."""
    out = ["--out", str(tmp_path)] if argv[0] in ("sim", "run") else ["--log", str(tmp_path)]
    with pytest.raises(SessionStarted):
        main([*argv, *out])


def test_an_out_folder_others_can_write_on_the_way_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--out`` is walked like a log folder (``teleop.files.open_dir``): a folder on the way that
    another user could rename in (0777 without the sticky bit) is refused before any work."""
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    err = _error(["sim", "--duration", "0.1", "--out", str(shared / "out")], capsys)
    assert f"--out {shared / 'out'}: the folder {shared} on the way is writable by other users" in err
    assert not (shared / "out").exists()


@pytest.mark.skipif(os.geteuid() != 0, reason="planting a symlink as another user (nobody) needs root")
@pytest.mark.parametrize("command", [["sim", "--duration", "0.1"], ["sweep", "--duration", "0.1"]])
def test_an_out_folder_that_is_another_users_symlink_is_never_written_through(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: list[str]
) -> None:
    """A symlink planted as ``--out`` by another user in a sticky shared folder (``/tmp``'s kind)
    is refused, and nothing lands where it points."""
    sticky, victim = tmp_path / "sticky", tmp_path / "victim"
    sticky.mkdir()
    sticky.chmod(0o1777)
    victim.mkdir()
    (sticky / "out").symlink_to(victim)
    os.lchown(sticky / "out", 65534, 65534)
    err = _error([*command, "--out", str(sticky / "out")], capsys)
    assert "is a symlink of uid 65534 that another user could have placed" in err
    assert list(victim.iterdir()) == []
