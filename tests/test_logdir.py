"""Logs never lost, and never trusted (issue 21, items 3-5).

A run's files are new files (``shell.logdir``): a restart keeps the earlier record, a planted
symlink is never written through, two processes of a role never share a file, a full disk is one
line.  A killed writer is reported and the chunks it wrote stay readable; ``teleop report`` pairs
logs by session, reports a killed process's log from its ticks, never opens a path a log names,
and gives one ``teleop: error:`` line for a hostile log.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from shell import logdir
from teleop import files
from teleop.offline.logfile import LogError, iter_ticks, read_session, read_summary
from tests.ran import RAN
from tests.waiting import ticks_logged, udp_bound, wait_for

TELEOP = [sys.executable, "-m", "teleop.cli"]
LINK = ["--duration", "1", "--netem-forward"]


# --- the summary, wherever the writer put it -----------------------------------------------------
def _mcap(path: Path, chunk_size: int, declare_first: bool = False, finish: bool = True) -> None:
    """A log like the writer process's (foxglove's writer, zstd chunks): the session message, 50
    events, the summary.  ``declare_first``: the summary's channel is used once at the start (a
    channel declared long before its message); ``finish``: the footer is written (not: killed)."""
    import foxglove
    from foxglove.mcap import MCAPCompression, MCAPWriteOptions

    from shell.mcaplog import SCHEMAS

    ctx = foxglove.Context()
    opts = MCAPWriteOptions(compression=MCAPCompression.Zstd, chunk_size=chunk_size)
    w = foxglove.open_mcap(str(path), context=ctx, writer_options=opts)
    ch = {n: foxglove.Channel(f"/operator/{n}", schema=SCHEMAS[n], context=ctx) for n in SCHEMAS}
    ch["session"].log(json.dumps({"params": {"session": 7}}).encode(), log_time=0)
    if declare_first:
        ch["summary"].log(json.dumps({"early": True}).encode(), log_time=0)
    for i in range(50):
        ch["events"].log(json.dumps({"t": i, "event": "e", "detail": "x" * 40}).encode(), log_time=i)
    if finish:
        ch["summary"].log(json.dumps({"params": {"session": 7}, "end_t": 1.0}).encode(), log_time=99)
        w.close()
    else:
        del w  # no summary, no footer: as a writer killed mid-session leaves it
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _chunks_declaring_and_holding(path: Path, topic: str) -> tuple[list[int], list[int]]:
    """Which chunks hold ``topic``'s Channel record and which its messages (file order)."""
    from teleop.offline.logfile import _OP_CHUNK, _chunk_payloads, _walk

    with _walk(path) as walk:
        bodies = [body for op, body in walk.records() if op == _OP_CHUNK]
        channels: dict[int, str] = dict(walk.channels)
        declared, holding = [], []
        for i, body in enumerate(bodies):
            known = topic in channels.values()
            got = _chunk_payloads(walk.chunk_records(body), channels)
            declared += [i] if not known and topic in channels.values() else []
            holding += [i] if topic in got else []
    return declared, holding


def test_the_summary_is_read_when_its_channel_is_declared_a_chunk_before_it(tmp_path: Path) -> None:
    """The writer declares a channel in the chunk it is filling, then closes that chunk if full and
    logs the message in the next: the summary's channel one chunk before the summary.  Read from
    the last chunk alone, such a log's summary was missing (a report said so once in ~100 runs)."""
    path = tmp_path / "operator.mcap"
    _mcap(path, chunk_size=1)  # every chunk full after one message: the split every time
    declared, holding = _chunks_declaring_and_holding(path, "/operator/summary")
    assert len(declared) == 1 and holding == [declared[0] + 1]  # the layout this test is about
    assert read_summary(path) == {"params": {"session": 7}, "end_t": 1.0}


def test_the_summary_is_found_when_its_channel_was_declared_long_before(tmp_path: Path) -> None:
    """A finished file whose last two chunks do not declare the summary's channel is read whole,
    and the summary is the channel's last message (the one logged last)."""
    path = tmp_path / "operator.mcap"
    _mcap(path, chunk_size=1, declare_first=True)
    declared, holding = _chunks_declaring_and_holding(path, "/operator/summary")
    assert len(declared) == 1 and declared[0] + 2 < holding[-1]  # out of the last two chunks' reach
    assert read_summary(path) == {"params": {"session": 7}, "end_t": 1.0}


def test_a_killed_writers_log_has_no_summary(tmp_path: Path) -> None:
    path = tmp_path / "operator.mcap"
    _mcap(path, chunk_size=1, finish=False)
    assert read_summary(path) == {}
    assert read_session(path)["params"]["session"] == 7


# --- files in the log folder --------------------------------------------------------------------
def test_a_symlink_planted_in_the_log_folder_is_never_written_through(tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.write_text("precious")
    logs = tmp_path / "logs"
    logs.mkdir()
    for name in ("operator.mcap", "operator.json", "operator-7.json"):
        (logs / name).symlink_to(victim)
    got = logdir.reserve(logs, "operator", 7)
    assert got.mcap.name == "operator-7-2.mcap" and got.summary.name == "operator-7-2.json"
    assert not got.mcap.is_symlink() and got.mcap.stat().st_size == 0
    # The summary's name taken by a symlink since: refused, not followed.
    (logs / "operator-7-2.json").symlink_to(victim)
    err = logdir.write_summary(got.summary, {"x": 1})
    assert err is not None and "File exists" in err
    assert victim.read_text() == "precious"
    assert not [p for p in logs.iterdir() if p.name.endswith(".tmp")]


def test_a_restart_with_the_same_folder_keeps_both_records(tmp_path: Path) -> None:
    first = logdir.reserve(tmp_path, "teleoperator", 9)
    first.mcap.write_bytes(b"5000 ticks")
    assert logdir.write_summary(first.summary, {"ticks": 5000}) is None
    second = logdir.reserve(tmp_path, "teleoperator", 9)  # the same session, rejoined
    third = logdir.reserve(tmp_path, "teleoperator", 10)
    assert [f.mcap.name for f in (first, second, third)] == [
        "teleoperator.mcap",
        "teleoperator-9.mcap",
        "teleoperator-10.mcap",
    ]
    assert first.mcap.read_bytes() == b"5000 ticks"
    assert json.loads(first.summary.read_text()) == {"ticks": 5000}
    assert logdir.write_summary(first.summary, {"ticks": 192}) is not None  # never over a record
    assert json.loads(first.summary.read_text()) == {"ticks": 5000}


def test_two_processes_of_a_role_never_share_a_file(tmp_path: Path) -> None:
    """Two robots with one --log and the same session id: each gets its own file (O_EXCL)."""
    a, b = logdir.reserve(tmp_path, "teleoperator", 5), logdir.reserve(tmp_path, "teleoperator", 5)
    assert a.mcap != b.mcap and (a.dev, a.ino) != (b.dev, b.ino)
    fd = files.open_reserved(a.mcap, a.dev, a.ino)
    os.close(fd)
    with pytest.raises(files.FileRefused, match="not the file this process created"):
        files.open_reserved(a.mcap, b.dev, b.ino)


def test_a_log_folder_others_can_write_is_refused_in_one_line(tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    logs.chmod(0o777)
    with pytest.raises(files.FileRefused, match="writable by other users"):
        logdir.reserve(logs, "operator", 1)
    assert list(logs.iterdir()) == []


def test_a_full_disk_is_one_line_and_leaves_no_partial_summary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    err = logdir.save_summary(tmp_path, "teleoperator", {"log": {"mcap": "teleoperator-3.mcap"}})
    assert err is not None and "No space left on device" in err
    line = capsys.readouterr().err
    assert line == f"teleop teleoperator: error: {err}\n"
    assert list(tmp_path.iterdir()) == []  # no empty teleoperator-3.json, no temporary file


# --- a killed writer ------------------------------------------------------------------------------
@pytest.mark.integration  # the log's writer process
def test_a_killed_writer_is_reported_and_its_chunks_stay_readable(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    from shell.mcaplog import McapLog
    from tests.test_logs import _pair, _run

    f = logdir.reserve(tmp_path, "operator", 7)
    log = McapLog(f.mcap, "operator", 1_700_000_000 * 10**9, file_id=(f.dev, f.ino))
    op, to = _pair((log, None))
    log.status("session", 0.0, {"role": "operator", "params": {"session": 7}})
    _run(op, to, range(3500))
    wait_for(lambda: f.mcap.stat().st_size >= 200_000, 30, "three chunks written")
    os.kill(log._proc.pid, signal.SIGKILL)
    log._proc.wait()
    _run(op, to, range(3500, 5000))  # the loop goes on
    log.close(op.summary())
    assert log.error is not None and "log writer process died (killed by signal 9)" in log.error
    assert "teleop operator: error: the log writer process died" in capfd.readouterr().err
    assert read_summary(f.mcap) == {}  # it never got the summary
    assert read_session(f.mcap)["params"]["session"] == 7
    ran = sum(int(b["ran"].sum()) for _, b in iter_ticks(f.mcap))
    assert ran >= 2000 and ran % 1000 == 0  # every chunk finished before the kill


@pytest.mark.integration  # the log's writer process
def test_a_full_disk_under_the_writer_is_one_line_and_the_log_stays_readable(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """The writer's file limited to 400 kB (RLIMIT_FSIZE, SIGXFSZ ignored: writes fail with EFBIG,
    as on a full disk): one console line, ``log.error``, and the chunks written before readable."""
    import resource

    from shell.mcaplog import McapLog
    from tests.test_logs import _pair, _run

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (400_000, 400_000))

    proc = subprocess.Popen(
        [sys.executable, "-m", "shell.mcaplog"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        preexec_fn=limit,
    )
    f = logdir.reserve(tmp_path, "operator", 7)
    log = McapLog(f.mcap, "operator", 1_700_000_000 * 10**9, process=proc, file_id=(f.dev, f.ino))
    op, to = _pair((log, None))
    _run(op, to, range(6000))
    log.close(op.summary())
    assert log.error is not None and "writing the log failed: File too large" in log.error
    err = capfd.readouterr().err
    assert err.count("error") == 1 and "teleop operator: error: writing the log failed" in err, err
    ran = sum(int(b["ran"].sum()) for _, b in iter_ticks(f.mcap))
    assert 1000 <= ran < 6000 and ran % 1000 == 0


# --- teleop report ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def genuine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One real session's two logs (`teleop run`, 3 s: three MCAP chunks a log)."""
    out = tmp_path_factory.mktemp("genuine")
    r = subprocess.run(
        [*TELEOP, "run", "--out", str(out), "--no-plots", "--no-sim", "--no-live", "--duration", "3"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode in RAN, r.stdout[-2000:] + r.stderr
    return out / "logs"


def _rewrite(
    src: Path, dst: Path, edit: Callable[[str, dict[str, Any]], dict[str, Any] | bytes | None]
) -> None:
    """``src`` copied to ``dst`` with the reference writer, each message through ``edit``
    (None: dropped; bytes: the message as is, JSON or not)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with src.open("rb") as f, dst.open("wb") as g:
        w = Writer(g)
        w.start()
        ids: dict[str, int] = {}
        for _, channel, message in make_reader(f).iter_messages():
            m = edit(channel.topic, json.loads(message.data))
            if m is None:
                continue
            if channel.topic not in ids:
                schema = w.register_schema(name=channel.topic, encoding="jsonschema", data=b"{}")
                ids[channel.topic] = w.register_channel(channel.topic, "json", schema)
            data = m if isinstance(m, bytes) else json.dumps(m).encode()
            w.add_message(ids[channel.topic], message.log_time, data, message.publish_time)
        w.finish()  # type: ignore[no-untyped-call]


def _copy(
    genuine: Path,
    tmp: Path,
    role: str,
    edit: Callable[[str, dict[str, Any]], dict[str, Any] | bytes | None],
) -> Path:
    """The genuine pair in a new folder, ``role``'s log rewritten through ``edit``."""
    logs = tmp / "logs"
    logs.mkdir()
    for r in ("operator", "teleoperator"):
        dst = logs / f"{r}.mcap"
        if r == role:
            _rewrite(genuine / f"{r}.mcap", dst, edit)
        else:
            dst.write_bytes((genuine / f"{r}.mcap").read_bytes())
    return logs


def _report(logs: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``teleop report`` in this process (its exit status, stdout and stderr): the imports once."""
    import contextlib
    import io

    from teleop.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            out_dir = [] if "--out" in args else ["--out", str(logs.parent)]
            code = main(["report", str(logs), "--no-plots", *out_dir, *args])
        except SystemExit as e:
            code = int(e.code or 0)
    return subprocess.CompletedProcess([], code, out.getvalue(), err.getvalue())


def _one_line(r: subprocess.CompletedProcess[str], says: str) -> None:
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(lines) == 1, r.stderr
    assert lines[0].startswith("teleop: error: ") and says in lines[0], lines[0]


def _params(**change: Any) -> Callable[[str, dict[str, Any]], dict[str, Any] | None]:
    def edit(topic: str, m: dict[str, Any]) -> dict[str, Any]:
        if topic.endswith(("/summary", "/session")):
            m["params"].update(change)
        return m

    return edit


@pytest.mark.integration
def test_a_report_on_a_franka_session_never_connects_to_the_arm(genuine: Path, tmp_path: Path) -> None:
    """The teleoperator's log names ``franka:ADDR`` with ADDR a loopback address of this test's, where
    a socket listens on libfranka's port as the "arm": the report (sim comparison asked for) says it
    skipped the sim because the robot is hardware, finishes, and nothing connected to the arm."""
    import random
    import socket

    arm = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    for _ in range(20):
        addr = f"127.{random.randrange(1, 255)}.{random.randrange(256)}.{random.randrange(1, 255)}"
        try:
            arm.bind((addr, 1337))  # libfranka's command port
            break
        except OSError:
            continue
    else:
        pytest.fail("no free loopback address for the arm")
    with arm:
        arm.listen(8)
        arm.setblocking(False)
        spec = f"franka:{addr}"

        def edit(topic: str, m: dict[str, Any]) -> dict[str, Any]:
            if topic.endswith("/summary") and isinstance(m.get("device"), dict):
                m["device"]["spec"] = spec
            return m

        logs = _copy(genuine, tmp_path, "teleoperator", edit)
        r = subprocess.run(
            [*TELEOP, "report", str(logs), "--no-plots", "--out", str(tmp_path)],
            capture_output=True,
            text=True,
            timeout=60,  # on main it connected and waited for the arm's answer forever
        )
        assert r.returncode in RAN, r.stderr
        assert f"teleop sim not re-run: the robot {spec} is hardware" in r.stdout, r.stdout
        rep = json.loads((tmp_path / "report.json").read_text())
        assert rep["devices"]["robot"]["spec"] == spec and "I_sim" not in rep["transparency"]
        with pytest.raises(BlockingIOError):
            arm.accept()  # nothing connected to the arm


@pytest.mark.integration
def test_a_killed_process_log_is_reported_from_its_ticks(genuine: Path, tmp_path: Path) -> None:
    """No /teleoperator/summary (the process was killed, its writer finished the file)."""
    logs = _copy(genuine, tmp_path, "teleoperator", lambda t, m: None if t.endswith("/summary") else m)
    r = _report(logs, "--no-sim")
    assert r.returncode in RAN, r.stderr
    assert "teleoperator SUMMARY MISSING" in r.stdout
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["summary_missing"] == ["teleoperator"] and rep["transparency"]["ticks_compared"] > 500
    assert "I_dc" not in rep["transparency"]  # the delays come from the summaries: none to take out


@pytest.mark.integration
def test_a_log_cut_off_by_a_killed_writer_is_reported(genuine: Path, tmp_path: Path) -> None:
    """A teleoperator log cut mid-chunk (no footer, no summary): the chunks before are reported."""
    logs = _copy(genuine, tmp_path, "none", lambda t, m: m)
    whole = (genuine / "teleoperator.mcap").read_bytes()
    chunks, pos = [], 8
    while pos < len(whole) and whole[pos] != 0x0F:  # the data section's records, up to DataEnd
        if whole[pos] == 0x06:
            chunks.append(pos)
        pos += 9 + int.from_bytes(whole[pos + 1 : pos + 9], "little")
    assert len(chunks) >= 2
    (logs / "teleoperator.mcap").write_bytes(whole[: chunks[-1] + 100])  # the last chunk cut off
    r = _report(logs, "--no-sim")
    assert r.returncode in RAN, r.stderr
    assert json.loads((tmp_path / "report.json").read_text())["summary_missing"] == ["teleoperator"]


@pytest.mark.integration
def test_the_report_never_opens_a_path_a_log_names(genuine: Path, tmp_path: Path) -> None:
    """A summary naming a trace (a FIFO here: opening it would hang) is reported; no sim re-run."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    logs = _copy(genuine, tmp_path, "operator", _params(netem_forward=f"trace {fifo}"))
    r = _report(logs)
    assert r.returncode in RAN, r.stderr
    assert "a report never opens a file a log names" in r.stdout


@pytest.mark.integration
def test_restarts_keep_every_record_and_the_report_pairs_by_session(genuine: Path, tmp_path: Path) -> None:
    """A second pair of another session beside the first: reported by --session, newest by default."""
    logs = tmp_path / "logs"
    logs.mkdir()
    for role in ("operator", "teleoperator"):
        (logs / f"{role}.mcap").write_bytes((genuine / f"{role}.mcap").read_bytes())
        _rewrite(genuine / f"{role}.mcap", logs / f"{role}-99.mcap", _params(session=99))
    first = read_summary(logs / "operator.mcap")["params"]["session"]
    r = _report(logs, "--no-sim", "--session", str(first))
    assert r.returncode in RAN, r.stderr
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["session"] == first and rep["logs"]["operator"] == "operator.mcap"
    r = _report(logs, "--no-sim")  # the newest pair: report.json is now its, the first one kept
    assert r.returncode in RAN, r.stderr
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["session"] == 99 and rep["logs"]["teleoperator"] == "teleoperator-99.mcap"
    assert json.loads((tmp_path / "report-99.json").read_text()) == rep
    assert json.loads((tmp_path / f"report-{first}.json").read_text())["session"] == first
    assert not list(tmp_path.glob("*.new*"))


def _dof_bomb(n: int, only: int | None = None) -> Callable[[str, dict[str, Any]], dict[str, Any]]:
    """Every signals message (or tick ``only``'s) with ``n`` values per vector."""

    def edit(topic: str, m: dict[str, Any]) -> dict[str, Any]:
        if topic.endswith("/signals") and only in (None, m["k"]):
            m["v"] = m["f"] = [0.0] * n
        return m

    return edit


def _drop_key(key: str) -> Callable[[str, dict[str, Any]], dict[str, Any]]:
    def edit(topic: str, m: dict[str, Any]) -> dict[str, Any]:
        if topic.endswith("/summary"):
            m.pop(key)
        return m

    return edit


@pytest.mark.integration
@pytest.mark.parametrize(
    ("edit", "says"),
    [
        (_dof_bomb(1000), "v has 1000 values (at most 64 DoF)"),
        (_dof_bomb(100_000, only=5), "a /ROLE/signals message of 1000"),  # bytes: before parsing
        (_params(dof=10**9), "dof must be"),
        (_params(duration=1e30), "duration must be"),
        (_params(dt=0.0), "dt must be"),  # was ZeroDivisionError
        (_params(codec="dct:5"), "codec"),  # was CodecError
        (_params(b="20"), "b must be"),  # was TypeError
        (_drop_key("loop"), "KeyError: 'loop'"),  # was a KeyError traceback
        (_params(session="x"), "name no session id"),
    ],
)
def test_a_hostile_log_is_one_line(
    genuine: Path, tmp_path: Path, edit: Callable[[str, dict[str, Any]], dict[str, Any] | None], says: str
) -> None:
    _one_line(_report(_copy(genuine, tmp_path, "operator", edit)), says)


def test_a_chunk_that_asks_for_too_much_memory_is_refused(tmp_path: Path) -> None:
    """A chunk header claiming 1.5 GB uncompressed: refused before anything is decompressed."""
    from mcap.writer import Writer

    path = tmp_path / "operator.mcap"
    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema(name="s", encoding="jsonschema", data=b"{}")
        ch = w.register_channel("/operator/signals", "json", schema)
        w.add_message(ch, 0, b'{"k":0,"t":0,"v":[0],"f":[0]}', 0)
        w.finish()  # type: ignore[no-untyped-call]
    data = bytearray(path.read_bytes())
    at = data.index(b"\x06", 8)  # the chunk record: opcode, length, start, end, uncompressed size
    data[at + 25 : at + 33] = (1_500_000_000).to_bytes(8, "little")
    path.write_bytes(bytes(data))
    with pytest.raises(LogError, match="a chunk of 1500000000 bytes uncompressed"):
        list(iter_ticks(path))


def test_tick_jumps_are_bounded_in_all(tmp_path: Path) -> None:
    """Many jumps each under MAX_GAP_TICKS add up to hours of work: refused by their sum."""
    from teleop.offline import logfile
    from tests.test_logs import _mcap, _sig

    jump = logfile.MAX_GAP_TICKS // 4
    path = _mcap(tmp_path / "operator.mcap", [_sig(i * jump) for i in range(6)])
    with pytest.raises(LogError, match="ticks skipped: not a session"):
        list(iter_ticks(path))
    with pytest.raises(LogError, match="beyond the session's 1000 ticks"):
        list(iter_ticks(_mcap(tmp_path / "operator-2.mcap", [_sig(0), _sig(5000)]), max_tick=1000))


@pytest.fixture(scope="module")
def traced(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A real session over a trace link (`teleop run --netem-forward 'trace FILE'`): its logs, and
    the trace, moved away afterwards (the logs copied to another host)."""
    out = tmp_path_factory.mktemp("traced")
    trace = out / "link.trace"
    trace.write_text("".join(f"{i}\n" for i in range(1, 101)))
    r = subprocess.run(
        [*TELEOP, "run", "--out", str(out), "--no-plots", "--no-sim", "--no-live", *LINK, f"trace {trace}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode in RAN, r.stderr
    kept = out / "kept.trace"
    trace.rename(kept)
    return out / "logs", kept


@pytest.mark.integration
def test_a_trace_run_is_reported_on_another_host_and_re_simulated_with_the_named_file(
    traced: tuple[Path, Path], tmp_path: Path
) -> None:
    logs, trace = traced
    src = read_session(logs / "operator.mcap")["traces"]["forward"]
    assert src["bytes"] == trace.stat().st_size and len(src["sha256"]) == 64
    r = _report(logs, "--out", str(tmp_path / "a"))  # the trace's path is gone: no traceback
    assert r.returncode in RAN, r.stderr
    assert "pass the same trace file with --trace FILE" in r.stdout and src["sha256"][:16] in r.stdout
    other = tmp_path / "other.trace"
    other.write_text("1\n2\n")
    r = _report(logs, "--out", str(tmp_path / "b"), "--trace", str(other))  # not the same file
    assert (
        r.returncode in RAN
        and "I_sim" not in json.loads((tmp_path / "b" / "report.json").read_text())["transparency"]
    )
    r = _report(logs, "--out", str(tmp_path / "c"), "--trace", str(trace))
    assert r.returncode in RAN, r.stderr
    rep = json.loads((tmp_path / "c" / "report.json").read_text())
    assert "sim_skipped" not in rep and rep["transparency"]["I_sim"] > 0
    _one_line(_report(logs, "--out", str(tmp_path / "d"), "--trace", "/dev/zero"), "a character device")


@pytest.mark.integration
def test_a_process_killed_mid_session_leaves_a_log_the_report_reads(tmp_path: Path) -> None:
    """kill -9 of the operator: its writer sees its pipe close and finishes the file (no summary);
    `teleop report` reports the session from the ticks and says the summary is missing."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    logs = tmp_path / "logs"
    common = ["--insecure", "--no-rt", "--quiet", "--log", str(logs)]
    to = subprocess.Popen([*TELEOP, "teleoperator", "--listen", f"127.0.0.1:{port}", *common])
    try:
        wait_for(lambda: udp_bound(port), 60, "the teleoperator's socket")
        op = subprocess.Popen(
            [*TELEOP, "operator", "--peer", f"127.0.0.1:{port}", "--duration", "4", *common]
        )
        # Killed mid-session, with more than the 1000 ticks the report must compare.
        wait_for(lambda: ticks_logged(logs / "operator.mcap") >= 1500, 60, "1500 ticks", poll=0.2)
        op.kill()
        op.wait()
        assert to.wait(timeout=30) in RAN
    finally:
        if to.poll() is None:
            to.kill()

    def finished() -> bool:  # the writer, in its own group, finishes the file
        try:
            return bool(read_session(logs / "operator.mcap"))
        except LogError:  # still being finished
            return False

    wait_for(finished, 10, "the killed operator's log, finished by its writer")
    assert read_summary(logs / "operator.mcap") == {} and not (logs / "operator.json").exists()
    r = _report(logs, "--no-sim")
    assert r.returncode in RAN, r.stderr
    assert "operator     SUMMARY MISSING" in r.stdout
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["summary_missing"] == ["operator"] and rep["transparency"]["ticks_compared"] >= 1000


# --- issue 36: a report reads only logs it can trust ---------------------------------------------
@pytest.mark.integration
@pytest.mark.skipif(os.geteuid() != 0, reason="planting a log as another user (nobody) needs root")
def test_a_log_another_user_planted_in_a_shared_folder_is_not_used(genuine: Path, tmp_path: Path) -> None:
    """A sticky folder (as /tmp) stops others replacing our logs, not adding theirs: nobody's newer
    operator log of the same session, with other figures, is flagged and ignored."""
    import shutil
    import tempfile

    base = Path(tempfile.mkdtemp(prefix="teleop-shared-", dir="/tmp"))  # nobody must reach it
    try:
        base.chmod(0o755)
        logs = base / "logs"
        logs.mkdir()
        for role in ("operator", "teleoperator"):
            (logs / f"{role}.mcap").write_bytes((genuine / f"{role}.mcap").read_bytes())
        honest = _report(logs, "--no-sim", "--out", str(tmp_path / "honest"))
        assert honest.returncode in RAN, honest.stderr
        logs.chmod(0o1777)
        sid = read_summary(genuine / "operator.mcap")["params"]["session"]

        def louder(topic: str, m: dict[str, Any]) -> dict[str, Any]:
            if topic.endswith("/signals"):
                m["v"] = [10 * x for x in m["v"]]
            return m

        crafted = base / "crafted.mcap"  # (nobody cannot read pytest's folders)
        _rewrite(genuine / "operator.mcap", crafted, louder)
        crafted.chmod(0o644)
        planted = logs / f"operator-{sid}.mcap"
        subprocess.run(
            [
                "setpriv",
                "--reuid=nobody",
                "--regid=nogroup",
                "--clear-groups",
                "cp",
                str(crafted),
                str(planted),
            ],
            check=True,
            timeout=30,
        )
        assert (
            planted.stat().st_uid != 0
            and planted.stat().st_mtime_ns > (logs / "operator.mcap").stat().st_mtime_ns
        )
        r = _report(logs, "--no-sim", "--out", str(tmp_path / "shared"))
        assert r.returncode in RAN, r.stderr
        assert f"note: ignored {planted}: owned by uid" in r.stdout
        rep = json.loads((tmp_path / "shared" / "report.json").read_text())
        want = json.loads((tmp_path / "honest" / "report.json").read_text())
        assert rep["logs"]["operator"] == "operator.mcap"
        assert rep["transparency"] == want["transparency"] and rep["phases"] == want["phases"]
    finally:
        shutil.rmtree(base, ignore_errors=True)


@pytest.mark.integration
def test_two_logs_of_one_session_and_role_are_an_error_naming_both(genuine: Path, tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    for role in ("operator", "teleoperator"):
        (logs / f"{role}.mcap").write_bytes((genuine / f"{role}.mcap").read_bytes())
    sid = read_summary(genuine / "operator.mcap")["params"]["session"]
    (logs / f"teleoperator-{sid}.mcap").write_bytes((genuine / "teleoperator.mcap").read_bytes())
    r = _report(logs, "--no-sim")
    _one_line(r, f"holds 2 teleoperator logs of session {sid} (")
    assert f"teleoperator-{sid}.mcap" in r.stderr and "(teleoperator.mcap" in r.stderr


# --- issue 36: hostile logs give one line ----------------------------------------------------------
def _nested(topic: str, depth: int, only: int | None = 5) -> Callable[[str, dict[str, Any]], Any]:
    """``topic``'s message (a per-tick one: tick ``only``'s) with a list nested ``depth`` deep."""

    done: list[bool] = []  # the first message at or after tick ``only``: a stall may skip that one

    def edit(t: str, m: dict[str, Any]) -> Any:
        if t.endswith(f"/{topic}") and not done and (only is None or m.get("k", -1) >= only):
            done.append(True)
            return json.dumps(m).encode()[:-1] + b', "x": ' + b"[" * depth + b"]" * depth + b"}"
        return m

    return edit


def _number(topic: str, field: str, value: Any) -> Callable[[str, dict[str, Any]], Any]:
    done: list[bool] = []  # the first message from tick 2500 on: a stall may skip that one

    def edit(t: str, m: dict[str, Any]) -> Any:
        if t.endswith(f"/{topic}") and not done and m.get("k", -1) >= 2500:
            done.append(True)
            m[field] = [value] * len(m[field]) if isinstance(m[field], list) else value
            if value == "DIGITS":  # 5000 digits: more than Python reads as an int
                return json.dumps(m).replace('"DIGITS"', "1" + "0" * 5000).encode()
        return m

    return edit


@pytest.mark.integration
@pytest.mark.parametrize(
    ("edit", "says"),
    [
        (_nested("summary", 100_000, None), "/operator/summary: JSON nested deeper than 32 levels"),
        (_nested("summary", 40, None), "/operator/summary: JSON nested deeper than 32 levels"),
        (_nested("signals", 5000), "a /ROLE/signals message nests deeper than JSON is read"),
        (_nested("energy", 5000), "a /ROLE/energy message nests deeper than JSON is read"),
        (_number("signals", "v", 1e308), "a /ROLE/signals message has v = 1e+308 (at most 1e+15"),
        (_number("signals", "f", float("-inf")), "has f = -inf (at most 1e+15"),
        (_number("energy", "sent", 1e308), "a /ROLE/energy message has sent = 1e+308"),
        (_number("energy", "peer_epoch", 1e300), "has peer_epoch = 1e+300"),
        (_number("wire", "tx_wire", 1e308), "a /ROLE/wire message has tx_wire = 1e+308"),
        (_number("loop", "lateness_ns", -1e308), "has lateness_ns = -1e+308"),
        (_number("loop", "k", 1e308), "does not follow its schema: OverflowError"),
        (_number("signals", "v", "DIGITS"), "does not follow its schema"),  # beyond Python's int
    ],
)
def test_a_crafted_log_is_one_line_never_a_traceback_or_a_warning(
    genuine: Path, tmp_path: Path, edit: Callable[[str, dict[str, Any]], Any], says: str
) -> None:
    import warnings

    logs = _copy(genuine, tmp_path, "operator", edit)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a RuntimeWarning (overflow) fails the test
        _one_line(_report(logs, "--no-sim"), says)


@pytest.mark.integration
def test_extreme_numbers_in_a_summary_are_values_without_a_warning(genuine: Path, tmp_path: Path) -> None:
    import warnings

    def huge(topic: str, m: dict[str, Any]) -> dict[str, Any]:
        if topic.endswith("/summary"):
            m["energy"] = dict.fromkeys(m["energy"], 1e308)
            m["handshake_rtt_us"] = -1e308
            m["pid"] = "\x1b[2J\nnot a line of its own"  # printed: its control characters escaped
        return m

    logs = _copy(genuine, tmp_path, "operator", huge)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = _report(logs, "--no-sim")
    assert r.returncode in RAN and "Traceback" not in r.stderr, r.stderr
    assert "\x1b" not in r.stdout and "pid \\x1b[2J" in r.stdout  # shown, not obeyed


@pytest.mark.integration
def test_a_file_name_with_control_characters_stays_one_line(genuine: Path, tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    for role in ("operator", "teleoperator"):
        (logs / f"{role}.mcap").write_bytes((genuine / f"{role}.mcap").read_bytes())
    (logs / "operator-\x1b[31m\nplanted.mcap").write_bytes((genuine / "operator.mcap").read_bytes())
    r = _report(logs, "--no-sim")
    _one_line(r, "holds 2 operator logs of session")
    assert "operator-\\x1b[31m\\x0aplanted.mcap" in r.stderr and "\x1b" not in r.stderr
