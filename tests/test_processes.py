"""Two real OS processes on loopback: counts, compression, timing, shutdown, and clear errors.

These launch `teleop run` (or one side alone) for a few seconds.  Figures asserted exactly are the
ones the design makes exact (packet counts per codec rate, payload compression, sender and
receiver counts on a lossless loopback); figures that depend on a shared machine's scheduling are
asserted with a tolerance, and transparency is compared with `teleop sim` only when the report
says that no payload missed its tick (each miss is a zero-filled tick, reported).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from teleop.offline.logfile import read_log
from teleop.offline.sim import deliveries
from teleop.session.schedule import MAX_CATCHUP
from tests.ran import RAN
from tests.waiting import exited_ok, ticks_logged, udp_bound, wait_for

pytestmark = pytest.mark.integration

TELEOP = [sys.executable, "-m", "teleop.cli"]


def _run(
    tmp: Path, *args: str, timeout: float = 60
) -> tuple[subprocess.CompletedProcess[str], dict[str, Any]]:
    out = tmp / "run"
    r = subprocess.run(
        [*TELEOP, "run", "--out", str(out), "--no-plots", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    rep = json.loads((out / "report.json").read_text()) if (out / "report.json").exists() else {}
    return r, rep


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie of a reaped child cannot linger: the launcher waited for it.
    status = Path(f"/proc/{pid}/status")
    return status.exists() and "State:\tZ" not in status.read_text()


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _misses(rep: dict[str, Any]) -> int:
    return sum(p["grace"]["missed"] for p in rep["processes"].values())


@pytest.mark.parametrize(
    "codec,per_dir,c_payload,tick_at",
    [
        ("eds:50", 60, 50.0, "wake"),
        ("none", 3000, 1.0, "wake"),
        ("ids:2", 1500, 2.0, "wake"),
        ("cq:8", 3000, 2.0, "wake"),
        ("none", 3000, 1.0, "deadline"),  # each tick run from its deadline (the loop before issue 22's)
    ],
)
def test_counts_and_compression(
    tmp_path: Path, codec: str, per_dir: int, c_payload: float, tick_at: str
) -> None:
    r, rep = _run(tmp_path, "--codec", codec, "--duration", "3", "--tick-at", tick_at)
    assert r.returncode in RAN, r.stderr
    assert rep["transport"] == "udp" and rep["codec"] == codec and rep["duration_s"] == 3.0
    logs = {r: read_log(tmp_path / "run" / "logs" / f"{r}.mcap")[1] for r in ("operator", "teleoperator")}
    for d, sender in (("forward", "operator"), ("backward", "teleoperator")):
        w = rep["wire"][d]
        skipped = rep["processes"][sender]["loop"]["skipped"]  # a host stall: those ticks send nothing
        # The teleoperator's iDS/eDS send phase follows its playout target (PROTOCOL 3.5), which the
        # host's jitter moves: each move of m ticks can add or drop up to m // K + 1 sends (a CI run
        # sent 1503 at ids:2, its phase moving 0 <-> 1 seven times); the log records the phase.
        moved = 0
        if d == "backward" and codec.split(":")[0] in ("ids", "eds"):
            k = int(codec.split(":")[1])
            phase = logs["teleoperator"]["send_phase"]
            phase = phase[phase >= 0]
            moves = np.abs(np.diff(phase))
            moved = 2 + int(np.sum(moves[moves > 0] // k + 1))
        assert per_dir - skipped - moved <= w["packets"] <= per_dir + moved  # the codec's rate, at the socket
        # The uncompressed stream: every tick of the session (a stall that skips past the end: fewer).
        assert 3000 - skipped <= w["baseline_packets"] <= 3000
        assert w["received_packets"] == w["packets"]  # loopback loses nothing: both ends agree
        assert w["received_wire_bytes"] == w["wire_bytes"]
        assert w["payload_bytes"] == w["packets"] * (4 if codec != "cq:8" else 2)  # 2 DoF
        if skipped == 0 and moved == 0:
            assert w["packets"] == per_dir and w["compression_payload"] == c_payload
        else:
            base = w["baseline_packets"] / 3000  # a stall past the end shortens the baseline too
            assert w["compression_payload"] == pytest.approx(c_payload * per_dir / w["packets"] * base)
        # On the wire the header weighs in: c_wire < c_payload unless every tick is sent (then a
        # stall's skipped ticks, which send nothing, raise both alike).
        assert 0.5 * c_payload < w["compression_wire"] <= 1.05 * c_payload * per_dir / w["packets"]
        assert w["min_instant_compression_wire"] <= w["compression_wire"] * 1.05
    for role, p in rep["processes"].items():
        loop = p["loop"]
        assert loop["ticks"] + loop["skipped"] == 3000, role  # every tick of the session ran or was skipped
        assert abs(loop["wall_s"] - 3.0) < 0.1, role  # at 1 kHz of wall-clock time
        # A scheduler that kept time (a bound, not a timing: a noisy host's stall moved the p50 to
        # 115 us in a fresh-clone CI run; bench.cpu measures the timing).
        assert loop["period_error_us"]["p50"] < 500, role
        # Datagrams leave once the loop reached the deadline, never before it (either mode).
        assert loop["send_lateness_us"]["p50"] >= loop["lateness_us"]["p50"] >= 0, role
        assert not _alive(p["pid"]), f"{role} process {p['pid']} still running"
        summary = json.loads((tmp_path / "run" / "logs" / f"{role}.json").read_text())
        f = summary["received"]["filter"]  # the kernel socket filter followed the endpoint's admission
        assert f["updates"] >= 1 and f["error"] is None, role
        assert f["strangers"] == ("none" if role == "operator" else "handshake"), role
    tr = rep["transparency"]
    assert 0 <= tr["I"] < 1.0  # bounded: an unstable or ringing loop gives I >> 1
    if _misses(rep) == 0:
        assert tr["I"] == pytest.approx(tr["I_sim"], rel=0.05)
    # The sim with the run's own deliveries (each payload at the tick the real receiver took it) is
    # the real run: one code path, whatever the host's stalls did to the schedule (issue 37).  Exact
    # up to the order of the sums, unless a loop skipped ticks (those the real side never ran).
    rp = tr["replay"]
    if all(p["loop"]["skipped"] == 0 for p in rep["processes"].values()) and not any(
        rp["taken_early"].values()  # (a receiver that stalled past its peer's next tick: a CI run)
    ):
        assert rp["relative_difference"] < 1e-9, rp
    # Never taken: only the payloads the receiver's last tick came before (the rx sequence numbers
    # only grow, so on a lossless loopback those are a tail).  Lag 0 forward: the operator's last
    # payload late by a stall at the end is one (a fresh-clone CI run saw 1); a stall longer than
    # MAX_CATCHUP ticks would have skipped ticks instead.
    assert 0 <= rp["never_taken"]["forward"] <= MAX_CATCHUP + 1, rp
    # Not sent: the ticks the codec leaves out, and those a stall of the operator's loop skipped.
    assert rp["not_sent"]["forward"] <= 3000 - per_dir + rep["processes"]["operator"]["loop"]["skipped"]
    # Of the payloads taken late, those whose sender's loop began the sending tick half a period
    # late or more, counted again here from the two logs.
    for d, tx, rx in (("forward", "operator", "teleoperator"), ("backward", "teleoperator", "operator")):
        at = deliveries(logs[tx]["tx_seq"], logs[rx]["rx_seq"])
        lagged = (at >= 0) & (at - np.arange(at.size) > rp["lag_ticks"][d])
        began = np.zeros(at.size, dtype=np.int64)  # read_log keeps lateness_ns of the ticks that ran
        began[np.isfinite(logs[tx]["play_time_s"][: at.size])] = logs[tx]["lateness_ns"]
        assert rp["taken_late"][d] == int(np.count_nonzero(lagged)), (d, rp)
        assert rp["sender_late"][d] == int(np.count_nonzero(lagged & (began >= 500_000))), (d, rp)
    e = rep["energy"]
    assert e["forward"]["min_margin"] >= -1e-9 and e["backward"]["min_margin"] >= -1e-9
    assert rep["two_port_min_energy"] >= -1e-9


def test_report_contract_and_logs(tmp_path: Path) -> None:
    r, rep = _run(tmp_path, "--codec", "eds:50", "--duration", "2")
    assert r.returncode in RAN, r.stderr
    for role in ("operator", "teleoperator"):
        p = rep["processes"][role]
        assert isinstance(p["pid"], int)
        for k in ("ticks", "overruns", "major_faults"):  # (page faults that read from disk)
            assert isinstance(p["loop"][k], int)
        if os.path.exists("/proc/stat"):  # the hypervisor's steal over the session, all CPUs
            assert isinstance(p["loop"]["host_steal_ms"], float) and p["loop"]["host_steal_ms"] >= 0.0
        assert set(p["loop"]["period_error_us"]) >= {"p50", "p99", "p999", "max"}
    for d in ("forward", "backward"):
        assert set(rep["wire"][d]) >= {
            "packets",
            "payload_bytes",
            "wire_bytes",
            "baseline_packets",
            "baseline_wire_bytes",
            "compression_payload",
            "compression_wire",
            "min_instant_compression_wire",
        }
    assert isinstance(rep["transparency"]["I"], float)
    assert "teleop run: protocol scenario, codec eds:50" in r.stdout
    # Wire bytes are what the socket saw: each datagram's length plus 28 (UDP/IPv4).  Rebuild the
    # datagrams eds:50 must have sent (ticks 0, 50, ...; 2 DoF, 4-byte payload) and compare.
    import numpy as np

    from shell.mcaplog import read_log
    from teleop.session import auth, wire

    z = read_log(tmp_path / "run" / "logs" / "operator.mcap")[1]
    sent_ticks = np.flatnonzero(z["tx_wire"])
    per_tick = z["tx_wire"][sent_ticks]
    ran = np.flatnonzero(~np.isnan(z["play_time_s"]))
    # eDS counts its calls: every 50th tick the loop ran (ticks 0, 50, ... unless a stall skipped some).
    assert sent_ticks.tolist() == ran[::50].tolist()
    if rep["processes"]["operator"]["loop"]["skipped"] == 0:
        assert sent_ticks.tolist() == list(range(0, 2000, 50))
    for seq, (tick, counted) in enumerate(zip(sent_ticks.tolist(), per_tick.tolist(), strict=True)):
        pkt = wire.Packet(rep["session"], wire.FORWARD, seq, tick, tick * 1000, 2, bytes(4), 1.0)
        assert counted == auth.OVERHEAD + len(wire.encode(pkt)) + 28  # envelope, packet, UDP/IPv4
    assert rep["wire"]["forward"]["wire_bytes"] == int(per_tick.sum())
    # The simulation counts with the same port code: same keys, and on a lossless loopback the
    # same packets and bytes in both directions (issue 9).
    from teleop.session.port import WIRE_KEYS

    for d, sender in (("forward", "operator"), ("backward", "teleoperator")):
        assert tuple(rep["wire"][d]) == tuple(rep["sim_wire"][d]) == WIRE_KEYS
        # The same packets; the same bytes too unless a host stall made the real run differ from
        # the simulation's schedule: skipped ticks, or a playout target (which sets the
        # teleoperator's send phase, hence its ticks' msgpack sizes) that rose above its floor.
        targets = rep["playout"]["forward"]["target_ms"]
        same = rep["processes"][sender]["loop"]["skipped"] == 0 and targets["max"] == targets["p50"]
        keys: tuple[str, ...] = ("packets", "payload_bytes", "received_packets")
        keys += ("baseline_wire_bytes",) if same else ()
        for k in keys:
            assert rep["wire"][d][k] == rep["sim_wire"][d][k], (d, k)
        if same:
            # The send phase can also move while the target settles in the first ticks (below its
            # p50, which the summary does not show): a send that moves across a msgpack size
            # boundary of its header (t_us at tick 65/66: 2 bytes; tick at 127/128 and 255/256: 1
            # byte each) changes the bytes, never the packets.  One CI run in three saw 3785 vs 3787.
            slack = 4 if d == "backward" else 0
            assert abs(rep["wire"][d]["wire_bytes"] - rep["sim_wire"][d]["wire_bytes"]) <= slack, d


def _wait_for_logs(logs: Path, timeout_s: float = 60.0) -> None:
    """Until both processes' session logs hold 1000 ticks: both loops then tick.  A fixed sleep
    interrupted the start on a loaded host (the processes take seconds to import there)."""
    paths = [logs / f"{role}.mcap" for role in ("operator", "teleoperator")]
    wait_for(lambda: all(ticks_logged(p) >= 1000 for p in paths), timeout_s, "1000 ticks a side", poll=0.2)


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # what `cmd &` in a script gives its command


@pytest.mark.parametrize("inherited", ["default", "ignored"])
def test_ctrl_c_stops_both_cleanly(tmp_path: Path, inherited: str) -> None:
    out = tmp_path / "run"
    p = subprocess.Popen(
        [*TELEOP, "run", "--out", str(out), "--no-plots", "--duration", "30"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=_ignore_sigint if inherited == "ignored" else None,
    )
    _wait_for_logs(out / "logs")
    os.killpg(p.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole process group
    _, stderr = p.communicate(timeout=20)
    assert p.returncode == 130, stderr
    rep = json.loads((out / "report.json").read_text())
    for role, pr in rep["processes"].items():
        assert pr["completed"] is False
        assert 500 < pr["loop"]["ticks"] < 30000, role
        assert not _alive(pr["pid"]), f"{role} left running"
    assert rep["exit_codes"] == {"teleoperator": 130, "operator": 130}
    # The report is written, without re-running the sim (seconds of work after a Ctrl-C).
    assert rep["sim_skipped"].startswith("interrupted (Ctrl-C)") and "I_sim" not in rep["transparency"]


def test_peer_never_answers(tmp_path: Path) -> None:
    port = _free_port()
    t0 = time.monotonic()
    r = subprocess.run(
        [
            *TELEOP,
            "operator",
            "--insecure",
            "--peer",
            f"127.0.0.1:{port}",
            "--listen",
            "127.0.0.1:0",
            "--connect-timeout",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert r.returncode == 1
    assert f"peer 127.0.0.1:{port} never answered within 1 s" in r.stderr
    assert time.monotonic() - t0 < 10


def test_port_taken(tmp_path: Path) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        r = subprocess.run(
            [
                *TELEOP,
                "teleoperator",
                "--insecure",
                "--listen",
                f"127.0.0.1:{port}",
                "--connect-timeout",
                "1",
            ],
            capture_output=True,
            text=True,
            timeout=30,
        )
    assert r.returncode == 1
    assert f"cannot bind UDP 127.0.0.1:{port}" in r.stderr and "in use" in r.stderr


def test_teleoperator_rejects_a_different_codec_and_keeps_waiting(tmp_path: Path, key: str) -> None:
    """A hello it cannot accept is answered with the reason; the robot's endpoint keeps serving.
    An operator with another key is not answered at all."""
    from teleop.session import auth

    other_key = tmp_path / "other.key"
    auth.write_key_file(other_key, auth.generate_key())
    port = _free_port()
    to = _spawn("teleoperator", "--key-file", key, "--listen", f"127.0.0.1:{port}", "--codec", "cq:8")
    wait_for(lambda: udp_bound(port), 60, "the teleoperator's socket")

    def operator(key_file: str, codec: str) -> subprocess.CompletedProcess[str]:
        cmd = ["operator", "--key-file", key_file, "--peer", f"127.0.0.1:{port}", "--listen", "127.0.0.1:0"]
        cmd += ["--codec", codec, "--connect-timeout", "2", "--duration", "1"]
        return subprocess.run([*TELEOP, *cmd], capture_output=True, text=True, timeout=30)

    op = operator(key, "eds:50")
    assert op.returncode == 1
    assert "rejected the session: codec 'eds:50' differs from this teleoperator's 'cq:8'" in op.stderr
    stranger = operator(str(other_key), "cq:8")  # the right settings, the wrong key
    assert stranger.returncode == 1 and "never answered within 2 s" in stranger.stderr
    assert to.poll() is None  # still waiting for a good hello
    good = operator(key, "cq:8")
    assert "rejected" not in good.stderr
    _, to_err = to.communicate(timeout=30)
    assert good.returncode in RAN and to.returncode in RAN, (good.stderr, to_err)
    assert "rejected the operator: codec 'eds:50' differs" in to_err


@pytest.mark.parametrize(
    "args,msg",
    [
        (["run", "--codec", "zz"], "unknown codec 'zz'"),
        (["operator", "--peer", "nohostport"], "--peer must be HOST:PORT"),
        (["teleoperator", "--listen", "127.0.0.1:99999"], "port must be an integer 0..65535"),
    ],
)
def test_bad_arguments(args: list[str], msg: str) -> None:
    r = subprocess.run([*TELEOP, *args], capture_output=True, text=True, timeout=30)
    assert r.returncode == 2 and msg in r.stderr


def test_impaired_run_watchdog_and_observed_link(tmp_path: Path) -> None:
    """Real processes through the shim: the link figures are measured at the receivers, and the
    controller keeps the worst reconstruction (hold on loss) passive."""
    r, rep = _run(
        tmp_path,
        "--codec",
        "none",
        "--duration",
        "3",
        "--netem",
        "delay 10ms 2ms loss 5%",
        "--on-loss",
        "hold",
        "--no-sim",
    )
    assert r.returncode in RAN, r.stderr
    for d in ("forward", "backward"):
        lk, pv = rep["link"][d], rep["passivity"][d]
        assert lk["spec"] == "delay 10ms 2ms loss 5%"
        assert 0.03 < lk["loss"] < 0.07  # 3000 packets at 5%: +-5 sigma
        # 10 ms +-2 ms, flushed on the 1 ms tick grid.  The median: a stall of the shared host delays
        # every packet queued behind it and moves the mean (15.7 ms in one CI run), not the median.
        assert 9.5 < lk["delay_ms"]["p50"] < 13.0 and lk["delay_ms"]["mean"] > 9.5
        assert lk["reordered"] > 0  # netem: jitter without rate reorders
        assert pv["violations"] > 0 and pv["controller_active_ticks"] == pv["violations"]
        assert pv["min_margin"] >= -1e-9
        assert rep["energy"][d]["min_margin"] >= -1e-9
    assert "watchdog forward" in r.stdout and "violations" in r.stdout


def test_impaired_run_without_controller_is_seen_violating(tmp_path: Path) -> None:
    r, rep = _run(
        tmp_path,
        "--codec",
        "none",
        "--duration",
        "2",
        "--netem",
        "loss 10%",
        "--on-loss",
        "hold",
        "--no-controller",
        "--no-sim",
    )
    assert r.returncode in RAN, r.stderr
    assert sum(rep["passivity"][d]["violations"] for d in ("forward", "backward")) > 0
    assert min(rep["passivity"][d]["min_margin"] for d in ("forward", "backward")) < -1e-9


def _spawn(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([*TELEOP, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


#: A robot loop stalled this long by its host (its own summary's longest period) cannot be asked to
#: confirm a start within the operator's window (300 ms lead less a 50 ms margin, protocol.start_lead).
HOST_STALL_MS = 100.0


def _started_unless_the_host_stalled(
    op: subprocess.Popen[str], to: subprocess.Popen[str], logs: Path
) -> None:
    """``op`` exits 0; or it failed to get its start confirmed while the robot's own log shows its
    loop stalled by more than :data:`HOST_STALL_MS`: then the test is skipped, saying so.  Three
    fresh-clone runs of 2026-12-04 failed here with the robot skipping 108, 103 and 816 ticks at a
    time; the session had started on its side.  Twice the first session's longest stall was 103 ms
    (102.9 and 103.1), once 7 ms after its link loss, cause not found: a page read back from disk
    is one candidate (the runner now locks its memory), so the skip and the failure say the major
    page faults the robot counted.  Any other failure fails the test."""
    code = op.wait(timeout=30)
    if code in RAN:
        return
    err = op.stderr.read() if op.stderr is not None else ""
    to.send_signal(signal.SIGINT)  # its summaries are the evidence: let it write them
    to.wait(timeout=30)
    longest, faults, steal = 0.0, 0, 0.0
    for f in logs.glob("teleoperator*.json"):
        loop = json.loads(f.read_text()).get("loop") or {}
        longest = max(longest, (loop.get("period_error_us") or {}).get("max") or 0.0)
        faults += loop.get("major_faults") or 0  # pages read from disk: the memory lock's evidence
        steal += loop.get("host_steal_ms") or 0.0  # the hypervisor's, over each session
    seen = f"the robot's loop stalled {longest / 1e3:.0f} ms, {faults} major page faults"
    seen += f", host steal {steal:.0f} ms"
    if "did not confirm the start" in err and longest / 1e3 > HOST_STALL_MS:
        pytest.skip(f"{seen} (the start's window: 250 ms)")
    raise AssertionError(f"{op.args!r} exited {code} ({seen}); its stderr:\n{err[-4000:]}")


def test_teleoperator_restarted_mid_session_and_the_operator_recovers(tmp_path: Path, key: str) -> None:
    port, logs = _free_port(), tmp_path / "logs"
    to1 = _spawn(
        "teleoperator", "--key-file", key, "--listen", f"127.0.0.1:{port}", "--log", str(logs), "--quiet"
    )
    wait_for(lambda: udp_bound(port), 60, "the teleoperator's socket")
    op = _spawn(
        "operator",
        "--key-file",
        key,
        "--peer",
        f"127.0.0.1:{port}",
        "--listen",
        "127.0.0.1:0",
        "--codec",
        "none",
        "--duration",
        "5",
        "--log",
        str(logs),
        "--quiet",
    )
    # Killed once the session has run 1.5 s of its 5 (the new one joins the rest of it).
    wait_for(lambda: ticks_logged(logs / "operator.mcap") >= 1500, 60, "1500 ticks", poll=0.2)
    to1.kill()  # a crash: no bye, no logs
    to1.wait()
    # The outage is the new process's start (its imports alone outlast the 50 ms link timeout).
    to2 = _spawn(
        "teleoperator", "--key-file", key, "--listen", f"127.0.0.1:{port}", "--log", str(logs), "--quiet"
    )
    exited_ok(op)
    exited_ok(to2)
    o = json.loads((logs / "operator.json").read_text())
    # The restarted teleoperator's log is a new file: the killed one's record stays (no summary).
    session = o["params"]["session"]
    t = json.loads((logs / f"teleoperator-{session}.json").read_text())
    assert (logs / "teleoperator.mcap").stat().st_size > 0 and not (logs / "teleoperator.json").exists()
    assert o["completed"] and t["completed"] and t["joined_late"]
    assert o["passivity"]["link_lost_events"] == 1 and o["rejoin"]["rejoins"] == 1
    # It joined the running session on its clock: after tick 0, before the end.  Where depends on how
    # fast both processes started on the host (2000-2500 when quiet, 1930 seen under load).
    assert 0 < t["first_tick"] < 5000
    assert t["received"]["packets"] > 500  # and the operator's packets flowed again
    from teleop.offline import report
    from teleop.offline.logfile import checked_params

    rep = report.build(logs, "udp", compare_sim=False)
    for d in ("forward", "backward"):
        assert rep["energy"][d]["min_margin"] >= -1e-9, d  # no energy across the two incarnations
        assert rep["link"][d]["duplicates"] == 0 and rep["link"][d]["loss"] < 0.01  # per incarnation
    # The streamed report's figures are their whole-session definitions on real logs (one starts late).
    from tests.report_oracle import assert_fold_matches, figures

    assert rep["logs"] == {"operator": "operator.mcap", "teleoperator": f"teleoperator-{session}.mcap"}
    paths = (logs / "operator.mcap", logs / f"teleoperator-{session}.mcap")
    phases = report._phases(checked_params(paths[0], o["params"]), 5.0)
    assert_fold_matches(report.fold_logs(*paths, phases, 2, 1e-3), figures(*paths, phases, 1e-3))


def test_operator_restarted_mid_session_and_the_teleoperator_serves_the_new_one(
    tmp_path: Path, key: str
) -> None:
    port, logs = _free_port(), tmp_path / "logs"
    to = _spawn(
        "teleoperator", "--key-file", key, "--listen", f"127.0.0.1:{port}", "--log", str(logs), "--quiet"
    )
    wait_for(lambda: udp_bound(port), 60, "the teleoperator's socket")
    op1 = _spawn(
        "operator",
        "--key-file",
        key,
        "--peer",
        f"127.0.0.1:{port}",
        "--listen",
        "127.0.0.1:0",
        "--codec",
        "none",
        "--duration",
        "10",
        "--log",
        str(logs / "op1"),
        "--quiet",
    )
    wait_for(lambda: ticks_logged(logs / "op1" / "operator.mcap") >= 2000, 60, "2000 ticks", poll=0.2)
    op1.kill()
    op1.wait()
    # The outage is the new process's start (its imports alone outlast the 50 ms link timeout).
    op2 = _spawn(
        "operator",
        "--key-file",
        key,
        "--peer",
        f"127.0.0.1:{port}",
        "--listen",
        "127.0.0.1:0",
        "--codec",
        "none",
        "--duration",
        "2",
        "--log",
        str(logs),
        "--quiet",
    )
    _started_unless_the_host_stalled(op2, to, logs)
    exited_ok(to)
    # The replaced session's logs keep their names; the new session's are files of its own.
    first = json.loads((logs / "teleoperator.json").read_text())
    assert first["replaced_by_new_session"] and not first["completed"]
    assert first["passivity"]["link_lost_events"] >= 1  # it went to its safe state first (a stall: twice)
    later = list(logs.glob("teleoperator-*.json"))
    assert len(later) == 1
    new = json.loads(later[0].read_text())
    assert new["completed"] and new["params"]["session"] != first["params"]["session"]
    op2_loop = json.loads((logs / "operator.json").read_text())["loop"]
    assert new["received"]["packets"] == 2000 - op2_loop["skipped"]  # every tick it ran sent one


def test_a_recorded_hello_during_an_outage_does_not_replace_the_session(tmp_path: Path, key: str) -> None:
    """Issue 11: while the link is down, an authentic hello of another session (a recording: it
    holds the key, but nobody behind it knows our fresh nonce) must not take the session over."""
    from teleop.session import auth, protocol

    psk = auth.robot_key(auth.read_key_file(key), auth.DEFAULT_ROBOT_NAME)  # the robot keys derive from
    old = protocol.SessionParams(
        session=12345, codec="none", scenario="protocol", dof=2, b=20.0, full_scale=2.0, duration=15.0
    )
    recorded = protocol.OperatorHandshake(old, now_ns=1, timeout_s=1, psk=psk, nonce=bytes(16)).poll(1)[0]
    port, logs = _free_port(), tmp_path / "logs"
    to = _spawn("teleoperator", "--key-file", key, "--listen", f"127.0.0.1:{port}", "--log", str(logs))
    wait_for(lambda: udp_bound(port), 60, "the teleoperator's socket")
    op = _spawn(
        "operator", "--key-file", key, "--peer", f"127.0.0.1:{port}", "--listen", "127.0.0.1:0",
        "--codec", "none", "--duration", "5", "--log", str(logs / "op"), "--quiet",
    )  # fmt: skip
    wait_for(lambda: ticks_logged(logs / "op" / "operator.mcap") >= 2000, 60, "2000 ticks", poll=0.2)
    os.kill(op.pid, signal.SIGSTOP)  # an outage: the teleoperator's link is lost
    # A fixed wait, one of the suite's few: the outage's length is the scenario (4x the 50 ms link
    # timeout), not an event to wait for.
    time.sleep(0.2)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stranger:
        stranger.bind(("127.0.0.1", 0))
        stranger.settimeout(0.05)

        def answered() -> bytes | None:
            stranger.sendto(recorded, ("127.0.0.1", port))
            try:
                return stranger.recv(2048)
            except TimeoutError:
                return None

        welcomed = wait_for(answered, 5, "an answer to the recorded hello", poll=0)
        assert welcomed is not None  # (wait_for returns only what is true)
        # ... the takeover answers it (a retry: a cookie, no state) ...
    os.kill(op.pid, signal.SIGCONT)
    exited_ok(op)
    _, to_err = to.communicate(timeout=30)
    assert to.returncode in RAN, to_err
    assert auth.peek(welcomed) is not None
    t = json.loads((logs / "teleoperator.json").read_text())
    assert t["completed"] and not t["replaced_by_new_session"]  # ... but it never commits
    assert not list(logs.glob("teleoperator-*.json")) and "replaced" not in to_err
    assert t["passivity"]["link_lost_events"] >= 1  # the outage really happened


def test_an_outage_both_sides_see_leaves_the_session_whole(tmp_path: Path) -> None:
    """A 1.5 s outage in both directions (a Mahimahi trace with a gap, named to both processes by
    teleop run): the operator offers rejoins to its live teleoperator, which drops them; one
    session, one log per side, and the link comes back."""
    trace = tmp_path / "gap.trace"
    trace.write_text("\n".join(str(t) for t in [*range(1, 1501), *range(3000, 6001)]) + "\n")
    r, rep = _run(tmp_path, "--duration", "5", "--codec", "eds:50", "--netem", f"trace {trace}")
    assert r.returncode in RAN, r.stderr
    logs = tmp_path / "run" / "logs"
    o = json.loads((logs / "operator.json").read_text())
    t = json.loads((logs / "teleoperator.json").read_text())
    assert o["completed"] and t["completed"] and not t["replaced_by_new_session"] and not t["joined_late"]
    assert not list(logs.glob("teleoperator-*"))
    assert o["rejoin"]["offers"] >= 3 and o["rejoin"]["rejoins"] == 0
    assert t["rejoin"]["own_offers_ignored"] >= 1
    for side in (o, t):
        assert side["passivity"]["link_lost_events"] == 1, side["role"]
        rx = side["received"]  # the socket: its buffer (asked, obtained or a warning), the kernel's drops
        assert rx["rcvbuf_asked"] == 16 << 20
        assert rx["rcvbuf_bytes"] >= rx["rcvbuf_asked"] or side["warnings"]
        assert rx["kernel_drops"] == 0 and rx["oversize"] == 0 and rx["drain_budget_hits"] == 0
    for d in ("forward", "backward"):
        assert rep["energy"][d]["min_margin"] >= -1e-9, d


@pytest.mark.parametrize(
    "codec,extra",
    [("dct:20:2", []), ("pdp:1", []), ("pd:2", ["--transport", "zenoh"]), ("none", ["--rate-cap", "64kbit"])],
)
def test_issue10_codecs_and_rate_cap_in_real_processes(tmp_path: Path, codec: str, extra: list[str]) -> None:
    """Each new codec family (and the rate cap) runs in two real processes with the same spec as
    in `teleop sim`: counts agree at both ends, the channel stays passive, the cap holds."""
    r, rep = _run(tmp_path, "--codec", codec, "--duration", "3", *extra)
    assert r.returncode in RAN, r.stderr
    for d, sender in (("forward", "operator"), ("backward", "teleoperator")):
        w = rep["wire"][d]
        if "zenoh" in extra:  # CongestionControl.DROP gives up on a packet when Zenoh's threads starve
            assert 0.8 * w["packets"] <= w["received_packets"] <= w["packets"]
        else:
            assert w["received_packets"] == w["packets"] > 0
        skipped = rep["processes"][sender]["loop"]["skipped"]
        if codec == "dct:20:2":  # a frame of 20 ticks per payload, 2 coefficients x 2 DoF
            assert 150 - skipped // 20 - 1 <= w["packets"] <= 150
            assert w["payload_bytes"] == 8 * w["packets"]
        elif codec.startswith("pd"):
            assert w["packets"] < 1500  # a fraction of the ticks (start-up included)
        else:
            cap = rep["rate_cap"][d]
            assert cap["bps"] == 64_000 and cap["held"] and cap["peak_bytes_per_window"] <= 800
            assert cap["held_back"] > 0  # `none` wants 1000 packets/s: the cap had work to do
    assert rep["energy"]["forward"]["min_margin"] >= -1e-9
    assert rep["energy"]["backward"]["min_margin"] >= -1e-9
    assert 0 <= rep["transparency"]["I"] < 5.0
    if codec == "none":
        assert "rate cap forward" in r.stdout and "held;" in r.stdout
