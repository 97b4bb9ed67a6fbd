"""Issue 12: the chunked per-tick record, flat memory, streamed MCAP logs and the live view.

Sim-level (two ports joined in one process, no clock), except the last tests, which run two real
processes for a few seconds: a session without a fixed end stopped by a signal, and the peer's bye.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import os
import signal
import socket
import struct
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shell.mcaplog import PER_TICK_TOPICS, TOPICS, McapLog, read_log
from teleop.control import metrics
from teleop.session.link.counters import DirectionCounters
from teleop.session.link.quantiles import MOVE_PER_ADD, Quantiles
from teleop.session.logformat import STATE_TOPICS
from teleop.session.node import PortOptions
from teleop.session.port import MemorySink, Port, make_node
from tests.ran import RAN
from tests.waiting import ticks_logged, udp_bound, wait_for

TELEOP = [sys.executable, "-m", "teleop.cli"]


def _pair(sinks: tuple[Any, Any] | None = None, codec: str = "none") -> tuple[Port, Port]:
    ports = []
    for i, role in enumerate(("operator", "teleoperator")):
        node = make_node(
            role,
            scenario="protocol",
            dof=2,
            dt=1e-3,
            b=20.0,
            codec=codec,
            full_scale=2.0,
            session=7,
            options=PortOptions(),
        )
        ports.append(Port(node, sink=sinks[i] if sinks else None))
    return ports[0], ports[1]


def _run(op: Port, to: Port, ticks: range) -> None:
    """The simulation's order within a tick (teleop.offline.sim.run_case), over ``ticks``."""
    backward: list[bytes] = []
    for n in ticks:
        now = n * 1e-3
        for data in backward:
            op.receive(data, now, n)
        for data in op.tick(n, now):
            to.receive(data, now, n)
        op.sent(n, now)
        backward = to.tick(n, now)
        to.sent(n, now)


# --- the chunked record ------------------------------------------------------------------------
def test_chunks_cover_every_tick_run_across_boundaries_and_gaps() -> None:
    op, to = _pair()
    ran = [*range(0, 1200), *range(3500, 4100)]  # a stall skipped 1200..3499: two whole chunks
    _run(op, to, range(0, 1200))
    _run(op, to, range(3500, 4100))
    s = op.summary()
    assert isinstance(op.sink, MemorySink)
    assert [c.k0 for c in op.sink.chunks] == [0, 1000, 3000, 4000]
    a = op.sink.arrays()
    assert a["v"].shape == (4100, 2)
    assert list(np.flatnonzero(~np.isnan(a["play_time_s"]))) == ran
    assert np.isnan(a["v"][1200:3500]).all() and not np.isnan(a["v"][ran]).any()
    # The baseline counts every tick from the first to the last, the skipped ones included.
    assert s["sent"]["baseline_packets"] == 4100
    assert s["sent"]["packets"] == len(ran)  # codec none: one packet per tick run


def test_a_late_first_tick_does_not_make_a_window_of_one_packet() -> None:
    """A side whose first tick is not a chunk's first (a late joiner, or a loop whose first ticks a
    stall skipped) has no baseline before it: the windows start at its first tick, so eds:50's
    minimum instantaneous compression stays what it is from tick 0 (bench/soak.py once showed 1.0)."""
    late, _ = _pair(codec="eds:50")
    _run(late, _, range(1370, 6000))
    prompt, _ = _pair(codec="eds:50")
    _run(prompt, _, range(0, 6000))
    got = late.summary()["sent"]["min_instant_compression_wire"]
    assert got > 45 and abs(got / prompt.summary()["sent"]["min_instant_compression_wire"] - 1) < 0.05


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.integers(0, 300), min_size=1, max_size=3000),
    st.integers(1, 250),
    st.lists(st.integers(1, 900), max_size=8),
)
def test_min_instant_compression_streamed_equals_the_whole_session(
    sent: list[int], window: int, cuts: list[int]
) -> None:
    """Chunk by chunk (the sliding window carried across) gives the figure of the whole array."""
    s = np.asarray(sent, dtype=np.float64)
    b = np.full(s.size, 80.0)
    c = DirectionCounters(window_ticks=window)
    c.baseline_bulk(np.full(s.size, 52, dtype=np.int64), 4)  # totals: 80 B on the wire a tick
    c.wire_bytes = int(s.sum())
    c.payload_bytes = int(s.sum())
    bounds = sorted({0, s.size, *(x % (s.size + 1) for x in cuts)})
    for lo, hi in itertools.pairwise(bounds):
        c.window(b[lo:hi], s[lo:hi], b[lo:hi], s[lo:hi])
    got = c.summary()["min_instant_compression_wire"]
    want = metrics.min_instant_compression(b, s, window)
    assert got == want or (math.isinf(got) and math.isinf(want))


def test_memory_stays_flat_as_the_session_goes_on() -> None:
    """The record leaves with each chunk (here to a sink that drops it): 10 s more of a session
    adds no memory beyond noise (the old preallocated record held ~180 bytes a tick: 1.8 MB, twelve
    times the bound)."""

    class Drop:
        def write(self, chunk: object) -> None:
            pass

    op, to = _pair((Drop(), Drop()), codec="eds:50")
    _run(op, to, range(0, 5000))
    tracemalloc.start()
    try:
        _run(op, to, range(5000, 10000))
        before = tracemalloc.get_traced_memory()[0]
        _run(op, to, range(10000, 20000))
        after = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    assert after - before < 150_000, after - before


# --- streaming percentiles ---------------------------------------------------------------------
@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=1, max_size=400))
def test_quantiles_are_exact_until_binned_then_within_the_resolution(xs: list[float]) -> None:
    exact = Quantiles(exact=10_000)
    binned = Quantiles(exact=0, lo=1e-6, hi=1e4, rel=1e-3)
    for x in xs:
        exact.add(x)
        binned.add(x)
    qs = [0.0, 50.0, 99.0, 100.0]
    assert exact.percentiles(qs) == [float(v) for v in np.percentile(xs, qs)]
    # Binned: each percentile is the value of a sample's bin at the nearest rank (0.1 % wide).
    srt = np.sort(xs)
    for q, got in zip(qs, binned.percentiles(qs), strict=True):
        near = srt[
            max(0, math.ceil(q / 100 * (len(xs) - 1) - 1e-9) - 1) : math.ceil(q / 100 * (len(xs) - 1)) + 2
        ]
        assert any(abs(got - v) <= 1e-3 * abs(v) + 1e-6 for v in near), (q, got, near)
    assert binned.max_abs == max(abs(x) for x in xs)


def test_quantiles_bin_their_exact_samples_as_they_bin_later_ones() -> None:
    """Past ``exact`` samples the kept ones move into the bins a slice at a time with the later
    samples (one move stalled the caller ~41 ms), the rest when percentiles are asked: each lands
    in the bin the one-sample rule gives it, both signs, zero, below ``lo`` and above ``hi``."""
    rng = np.random.default_rng(22)
    xs = np.concatenate(
        [
            rng.choice([-1.0, 1.0], 20_000) * 10.0 ** rng.uniform(-12, 14, 20_000),
            [0.0, -0.0, 1.0, -1.0, 1e12, 2e12, 1e-3, 0.999],
            rng.integers(-2_000_000, 2_000_000, 5_000).astype(np.float64),  # ns, as the ticker adds
        ]
    )
    for exact in (len(xs) - 1, len(xs) - 3 * MOVE_PER_ADD - 7, 2 * MOVE_PER_ADD):  # moved by: asking,
        moved = Quantiles(exact=exact, lo=1.0, hi=1e12)  # partly by later adds, wholly by them
        one_by_one = Quantiles(exact=0, lo=1.0, hi=1e12)
        for x in xs:
            moved.add(float(x))
            one_by_one.add(float(x))
        qs = [0.0, 50.0, 99.0, 99.9, 100.0]
        assert moved.percentiles(qs) == one_by_one.percentiles(qs)
        assert moved._pos is not None and one_by_one._pos is not None
        assert moved._neg is not None and one_by_one._neg is not None
        np.testing.assert_array_equal(moved._pos, one_by_one._pos)
        np.testing.assert_array_equal(moved._neg, one_by_one._neg)
        assert moved.count == one_by_one.count == len(xs)


# --- MCAP --------------------------------------------------------------------------------------
@pytest.mark.integration  # the log's writer process
@pytest.mark.serial
def test_the_writer_process_yields_to_the_loops(tmp_path: Path) -> None:
    """The log's writer runs under SCHED_IDLE, so that a waking 1 kHz loop preempts it at once
    (bench/soak.py measured what a niced writer cost the loops' p99)."""
    log = McapLog(tmp_path / "operator.mcap", "operator", wall0_ns=0)
    try:
        pid = log._proc.pid
        # It sets its policy as it starts, before it imports.
        wait_for(lambda: os.sched_getscheduler(pid) == os.SCHED_IDLE, 30, "SCHED_IDLE")
    finally:
        log.close()
    assert log.error is None


@pytest.mark.integration  # the log's writer process
@pytest.mark.serial
def test_the_writer_finishes_at_the_processs_priority_once_no_loop_ticks(tmp_path: Path) -> None:
    """At the close the writer's threads leave SCHED_IDLE (with the privilege that takes): on a
    host whose cores other work keeps busy, an idle writer's backlog kept the process alive for
    tens of seconds after the session ended."""
    log = McapLog(tmp_path / "operator.mcap", "operator", wall0_ns=0)
    try:
        pid = log._proc.pid
        wait_for(lambda: os.sched_getscheduler(pid) == os.SCHED_IDLE, 30, "SCHED_IDLE")
        if os.geteuid() != 0:
            assert log.promote() is False  # refused without CAP_SYS_NICE: stays idle
            assert os.sched_getscheduler(pid) == os.SCHED_IDLE
            return
        assert log.promote() is True
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        assert tids and all(os.sched_getscheduler(t) == os.SCHED_OTHER for t in tids)
        nice = os.getpriority(os.PRIO_PROCESS, 0)
        assert all(os.getpriority(os.PRIO_PROCESS, t) == nice for t in tids)
    finally:
        log.close()
    assert log.error is None


@pytest.mark.integration  # the log's writer process
@pytest.mark.parametrize("promoted", [False, True])
def test_a_close_that_waits_for_an_idle_writer_says_why(
    promoted: bool, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """Without the privilege to promote the writer, a close that waits on it (here: the writer
    stopped for a second) prints one line saying why; promoted, the same wait prints none."""
    import threading

    from shell import mcaplog

    monkeypatch.setattr(mcaplog, "promote_writer", lambda proc: promoted)
    monkeypatch.setattr(mcaplog, "SLOW_CLOSE_S", 0.2)
    log = McapLog(tmp_path / "operator.mcap", "operator", wall0_ns=0)
    os.kill(log._proc.pid, signal.SIGSTOP)
    resume = threading.Timer(1.0, os.kill, (log._proc.pid, signal.SIGCONT))
    resume.start()
    try:
        log.close()
    finally:
        resume.join()
    err = capfd.readouterr().err
    said = err.count("teleop operator: finishing the log: its writer runs at idle priority")
    assert said == (0 if promoted else 1)
    assert log.error is None


def test_a_replaced_sessions_log_keeps_its_writer_idle_until_no_loop_ticks() -> None:
    """The log of a session a takeover replaced closes while the next session ticks: its writer
    stays under SCHED_IDLE until the process waits for it at the end, when it is promoted; a
    session that ended with nothing after it promotes its writer at the close."""
    import threading

    from shell import records as rec

    calls: list[str] = []
    promoted = threading.Event()

    class Log:
        path = None
        messages = dropped_chunks = 0
        live_port = error = None

        def event(self, *a: Any) -> None:
            pass

        def promote(self) -> bool:
            calls.append("promote")
            promoted.set()
            return True

        def close(self, summary: Any = None, timeout: float = 0.0, promote: bool = True) -> None:
            calls.append(f"close promote={promote}")
            if not promote:  # a backlog the idle writer cannot finish while the host is busy
                assert promoted.wait(10)

    class Summary:
        process = type("P", (), {"log": None})()

        def document(self, **kw: Any) -> dict[str, Any]:
            return {}

    r = rec.Records("operator", None, None, "127.0.0.1")
    r.logs[1] = Log()  # type: ignore[assignment]
    r.end(Summary(), 1, 1.0, "replaced", True)  # type: ignore[arg-type]
    r.logs[2] = Log()  # type: ignore[assignment]
    r.end(Summary(), 2, 1.0, "bye", False)  # type: ignore[arg-type]
    assert sorted(calls) == ["close promote=False", "close promote=True"]  # nothing promoted yet
    r.wait_finished()
    assert calls[-1] == "promote" and calls.count("promote") == 1


@pytest.mark.integration  # the log's writer process
def test_mcap_log_channels_counts_and_contents(tmp_path: Path) -> None:
    """Both sides log to ROLE.mcap; read back with the mcap library, the file has the documented
    channels (JSON, with a JSON schema each), one message per tick on each per-tick channel, and
    its arrays are the in-memory record's, bit for bit."""
    from mcap.reader import make_reader

    ticks = 2500
    logs = [
        McapLog(tmp_path / f"{r}.mcap", r, wall0_ns=1_700_000_000 * 10**9)
        for r in ("operator", "teleoperator")
    ]
    op, to = _pair((logs[0], logs[1]))
    _run(op, to, range(ticks))
    for log, port in zip(logs, (op, to), strict=True):
        log.status("session", 0.0, {"role": log.role})
        log.status("link", 1.0, {"t": 1.0, "link": port.observer.summary()})
        log.event(1.0, "link_lost", "test")
        summary = port.summary()
        log.close(summary)
        assert log.dropped_chunks == 0
    ref_op, ref_to = _pair()
    _run(ref_op, ref_to, range(ticks))
    ref_op.finish()
    assert isinstance(ref_op.sink, MemorySink)
    want = ref_op.sink.arrays()

    with (tmp_path / "operator.mcap").open("rb") as f:
        reader = make_reader(f)
        summary_rec = reader.get_summary()
        assert summary_rec is not None and summary_rec.statistics is not None
        topics = {c.topic: c for c in summary_rec.channels.values()}
        # The robot's state topics only where a device has a state (the built-in ones have none).
        assert set(topics) == {f"/operator/{n}" for n in TOPICS if n not in STATE_TOPICS}
        for ch in topics.values():
            assert ch.message_encoding == "json"
            assert summary_rec.schemas[ch.schema_id].encoding == "jsonschema"
        counts = {
            summary_rec.channels[i].topic: n for i, n in summary_rec.statistics.channel_message_counts.items()
        }
    for name in PER_TICK_TOPICS:
        assert counts[f"/operator/{name}"] == ticks, name
    for name in ("events", "summary", "session", "link"):
        assert counts[f"/operator/{name}"] == 1, name
    summary, arrays = read_log(tmp_path / "operator.mcap")
    assert summary["sent"]["packets"] == ticks
    for name in ("v", "f", "wave_out", "wave_in", "energy_sent", "energy_played", "tx_wire", "rx_wire"):
        np.testing.assert_array_equal(arrays[name], want[name], err_msg=name)
    np.testing.assert_array_equal(arrays["tx_seq"], want["tx_seq"])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def _live_client(port: int, want: int) -> tuple[set[str], list[dict[str, Any]]]:
    """A Foxglove WebSocket client: subscribe to every advertised channel, collect messages."""
    import websockets

    topics: set[str] = set()
    got: list[dict[str, Any]] = []
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]) as ws:  # type: ignore[list-item]
        subs: dict[int, str] = {}
        deadline = time.monotonic() + 10
        while len(got) < want and time.monotonic() < deadline:
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=1.0)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg.get("op") == "advertise":
                    new = []
                    for ch in msg["channels"]:
                        topics.add(ch["topic"])
                        sid = len(subs) + 1
                        subs[sid] = ch["topic"]
                        new.append({"id": sid, "channelId": ch["id"]})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
            elif frame[0] == 1:  # message data: opcode, subscription id u32, log time u64, payload
                sid, _log_time = struct.unpack_from("<IQ", frame, 1)
                got.append({"topic": subs[sid], **json.loads(frame[13:])})
    return topics, got


@pytest.mark.integration  # the log's writer process
def test_live_view_serves_the_channels_over_foxglove_websocket() -> None:
    port = _free_port()
    log = McapLog(None, "operator", wall0_ns=0, live_port=port)
    try:
        assert log.live_port == port  # the writer process is up and serving

        async def feed_and_listen() -> tuple[set[str], list[dict[str, Any]]]:
            client = asyncio.create_task(_live_client(port, want=30))
            for k in range(0, 4000, 20):  # fed until the client has what it wants, at 200 a second
                await asyncio.wait([client], timeout=0.005)
                msgs = {"signals": {"k": k, "t": k * 1e-3, "v": [0.1, 0.2], "f": [1.0, 2.0]}}
                log.live(k, k * 1e-3, msgs)
                if client.done():
                    break
            return await client

        topics, got = asyncio.run(feed_and_listen())
    finally:
        log.close()
    assert topics == {f"/operator/{n}" for n in TOPICS}
    signals = [m for m in got if m["topic"] == "/operator/signals"]
    assert len(signals) >= 10
    assert all(m["v"] == [0.1, 0.2] and m["k"] % 20 == 0 for m in signals)


# --- real processes ----------------------------------------------------------------------------
@pytest.mark.integration
def test_run_until_stopped_reports_and_both_exit_cleanly(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "run"
    p = subprocess.Popen(
        [*TELEOP, "run", "--out", str(out), "--no-plots", "--no-sim", "--no-live", "--duration", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    # Ctrl-C once both loops have ticked a while: both logs exist once a session has started (on a
    # loaded host the processes take seconds to import, and a fixed 3 s could interrupt the start).
    # Both processes' logs hold 1000 ticks (the checks below need 500 ticks of each loop).
    logs = [out / "logs" / f"{role}.mcap" for role in ("operator", "teleoperator")]
    wait_for(lambda: all(ticks_logged(p) >= 1000 for p in logs), 60, "1000 ticks in both logs", poll=0.2)
    os.killpg(p.pid, signal.SIGINT)  # Ctrl-C: the way an open session ends
    _, stderr = p.communicate(timeout=30)
    assert p.returncode in RAN, stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["until_stopped"] is True and rep["exit_codes"] == {"teleoperator": 0, "operator": 0}
    # What the process adds to its summary after the loop is in the MCAP file too.
    assert rep["security"]["auth"] == "blake2s-128" and rep["handshake"]["rtt_us"] > 0
    for role, pr in rep["processes"].items():
        assert pr["completed"] is True, role
        assert pr["loop"]["ticks"] > 500, role
        assert pr["event_loop"] in ("uvloop", "asyncio"), role
    assert 0.5 < rep["duration_s"] < 30
    # The scenario's phases are the open session's too (they were all empty: cut at duration 0).
    assert rep["phases"]["free"]["ticks"] > 500 and rep["phases"]["free"]["start"] == 0.0
    # A session longer than the simulation's cap is compared over the cap's ticks (here 0.5 s).
    from teleop.control import metrics
    from teleop.offline import report

    monkeypatch.setattr(report, "SIM_CAP_S", 0.5)
    rep = report.build(out / "logs", "udp", compare_sim=True)
    tr = rep["transparency"]
    assert tr["sim_s"] == 0.5 < rep["duration_s"] and tr["I_over_sim_s"] < tr["I"]
    a_op, a_to = (read_log(out / "logs" / f"{r}.mcap")[1] for r in ("operator", "teleoperator"))
    ok = ~(np.isnan(a_op["v"][:500]).any(axis=1) | np.isnan(a_to["v"][:500]).any(axis=1))
    v_op, v_to, f_op, f_to = (a[x][:500][ok] for x in ("v", "f") for a in (a_op, a_to))
    i_first = metrics.transparency(v_op, v_to, f_op, f_to, 1e-3)
    assert tr["I_over_sim_s"] == pytest.approx(i_first, rel=1e-9)
    assert tr["relative_difference"] == pytest.approx(abs(i_first - tr["I_sim"]) / tr["I_sim"])
    assert "over the first 0.5 s" in report.summary_text(rep)
    for role in ("operator", "teleoperator"):
        summary, arrays = read_log(out / "logs" / f"{role}.mcap")
        assert summary["params"]["duration"] == 0
        ran = int(np.count_nonzero(~np.isnan(arrays["play_time_s"])))
        assert ran == summary["loop"]["ticks"], role  # every tick run is in the log
    # Next to eq. (7), as teleop sim reports them: I_dc and the drift, folded from the same logs,
    # equal their whole-array definitions with the delays the receivers measured.
    dc = {d: round(ms) for d, ms in tr["delay_compensation_ms"].items()}
    n = min(len(a_op["v"]), len(a_to["v"]))
    ok = ~(np.isnan(a_op["v"][:n]).any(axis=1) | np.isnan(a_to["v"][:n]).any(axis=1))
    if not ok.all():  # a host stall skipped ticks: the whole-array definitions do not apply as they are
        pytest.skip("a tick was skipped (a host stall): I_dc is not comparable with the whole arrays")
    i_dc = metrics.delay_compensated(
        a_op["v"][:n], a_to["v"][:n], a_op["f"][:n], a_to["f"][:n], 1e-3, dc["forward"], dc["backward"]
    )
    assert tr["I_dc"] == pytest.approx(i_dc, rel=1e-9)
    assert tr["drift_m"] == pytest.approx(
        metrics.position_drift(a_op["v"][:n], a_to["v"][:n], 1e-3, dc["forward"])
    )
    assert "I_dc = " in report.summary_text(rep)


@pytest.mark.integration
def test_the_peers_bye_ends_an_open_session(tmp_path: Path) -> None:
    """SIGTERM to the operator alone: it says bye, and the teleoperator ends its loop, writes its
    log and exits 0 by itself; `teleop report` then builds the report from the two MCAP files."""
    port = _free_port()
    logs = tmp_path / "logs"
    common = ["--log", str(logs), "--insecure", "--no-rt", "--quiet"]
    to = subprocess.Popen([*TELEOP, "teleoperator", "--listen", f"127.0.0.1:{port}", *common], text=True)
    try:
        wait_for(lambda: udp_bound(port), 60, "the teleoperator's socket")
        op = subprocess.Popen(
            [*TELEOP, "operator", "--peer", f"127.0.0.1:{port}", "--duration", "0", *common], text=True
        )
        # The report below compares over 1000 ticks: let the teleoperator log more than that.
        wait_for(lambda: ticks_logged(logs / "teleoperator.mcap") >= 1500, 60, "1500 ticks", poll=0.2)
        op.send_signal(signal.SIGTERM)
        assert op.wait(timeout=20) in RAN
        assert to.wait(timeout=20) in RAN
    finally:
        for proc in (to,):
            if proc.poll() is None:
                proc.kill()
    t = json.loads((logs / "teleoperator.json").read_text())
    assert t["peer_said_bye"] is True and t["completed"] is True and t["stopped_by_signal"] is None
    r = subprocess.run(
        [*TELEOP, "report", str(logs), "--out", str(tmp_path / "rep"), "--no-plots", "--no-sim"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode in RAN, r.stderr
    assert r.stdout.startswith("teleop report: ")  # the command that printed it, not `teleop run`
    rep = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert rep["until_stopped"] is True and rep["transparency"]["ticks_compared"] > 1000


# --- the streamed report ------------------------------------------------------------------------
@pytest.mark.integration  # the log's writer process
def test_the_streamed_report_equals_the_whole_session_figures(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``teleop report`` folds both logs a block of ticks at a time (flat memory, any length); its
    figures equal their whole-array definitions (tests/report_oracle.py) on a session with forward
    loss, backward reordering, a teleoperator stall (ticks it did not run, payloads it took late),
    a teleoperator log that starts late and an operator log that ends early.  Small lookahead and
    plot budget, so blocks queue, the plots thin, and the lookup waits for the sender's log."""
    from teleop.offline import report
    from tests.report_oracle import assert_fold_matches, figures

    monkeypatch.setattr(report, "LOOKAHEAD_TICKS", 37)
    monkeypatch.setattr(report, "PLOT_POINTS", 1000)
    logs = [
        McapLog(tmp_path / f"{r}.mcap", r, wall0_ns=1_700_000_000 * 10**9)
        for r in ("operator", "teleoperator")
    ]
    op, to = _pair((logs[0], logs[1]), codec="ids:2")
    rng = np.random.default_rng(5)
    backward: list[tuple[int, bytes]] = []
    forward: list[bytes] = []
    ticks = 7000
    for n in range(ticks):
        now = n * 1e-3
        for _, data in [b for b in backward if b[0] <= n]:
            if n < 6500:  # the operator's log ends early: it stops at 6500
                op.receive(data, now, n)
        backward = [b for b in backward if b[0] > n]
        if n < 6500:
            for data in op.tick(n, now):
                if rng.random() >= 0.05:  # 5% forward loss
                    forward.append(data)
            op.sent(n, now)
        if n < 300 or 2200 <= n < 2260:  # the teleoperator joins at 300 and stalls 60 ticks
            continue
        for data in forward:
            to.receive(data, now, n)
        forward = []
        for data in to.tick(n, now):
            backward.append((n + int(rng.integers(0, 4)), data))  # 0-3 ticks late: reordered
        to.sent(n, now)
    for log, port in zip(logs, (op, to), strict=True):
        log.close(port.summary())
    phases = [("free", 0.0, 2.5), ("foam", 2.5, 5.0), ("wall", 5.0, 1e9)]
    want = figures(tmp_path / "operator.mcap", tmp_path / "teleoperator.mcap", phases, 1e-3)
    fold = report.fold_logs(tmp_path / "operator.mcap", tmp_path / "teleoperator.mcap", phases, 2, 1e-3)
    assert want["ticks"] == 6500 and want["phases"]["all"]["ticks"] == 6500 - 300 - 60
    assert want["min_margin"]["forward"] is not None and want["two_port"] is not None
    assert_fold_matches(fold, want)
    k, sig = fold.signals.get()
    assert fold.signals.stride == 8 and k.size <= 1000 and np.all(k % 8 == 0)  # 6500 ticks, thinned
    np.testing.assert_array_equal(sig["v_op"], read_log(tmp_path / "operator.mcap")[1]["v"][k])
    kb, bw = fold.bandwidth.get()
    wire = np.nan_to_num(read_log(tmp_path / "operator.mcap")[1]["tx_wire"])
    np.testing.assert_allclose(bw["fwd"], [wire[j - 99 : j + 1].sum() for j in kb])  # 100-tick windows


def _mcap(path: Path, messages: list[tuple[str, bytes]], chunk_size: int = 1 << 20) -> Path:
    """An MCAP file of raw JSON messages on ``/operator/TOPIC`` channels (the reference writer)."""
    from mcap.writer import Writer

    with path.open("wb") as f:
        w = Writer(f, chunk_size=chunk_size)
        w.start()
        ids: dict[str, int] = {}
        for i, (topic, data) in enumerate(messages):
            if topic not in ids:
                schema = w.register_schema(name=topic, encoding="jsonschema", data=b"{}")
                ids[topic] = w.register_channel(f"/operator/{topic}", "json", schema)
            w.add_message(ids[topic], log_time=i, data=data, publish_time=i)
        w.finish()  # type: ignore[no-untyped-call]
    return path


def _sig(k: Any, v: Any = (0.1, 0.2)) -> tuple[str, bytes]:
    return "signals", json.dumps({"k": k, "t": 0.0, "v": v, "f": [0.0, 0.0]}).encode()


@pytest.mark.parametrize(
    ("messages", "says"),
    [
        ([_sig(0), _sig(10**15)], "a jump of 1000000000000000 ticks"),  # no 10^15-tick allocation
        ([_sig(0), ("x", b""), _sig(10**15)], "tick 1000000000000000 after tick 0"),  # across chunks
        ([_sig(10**12)], "tick 1000000000000 after tick -1"),
        ([_sig(5), _sig(3)], "tick numbers must increase"),
        ([_sig(-1)], "tick numbers must increase"),
        ([_sig(0, "abc")], "does not follow its schema"),
        ([_sig(0, [1.0, [2.0]])], "does not follow its schema"),
        ([_sig("x")], "does not follow its schema"),
        ([("signals", b"not json")], "does not follow its schema"),
        ([("signals", b"[1, 2]")], "does not follow its schema"),
        ([_sig(0), _sig(1, [0.1, 0.2, 0.3])], "does not follow its schema"),
        ([_sig(0), ("x", b""), _sig(1, [0.1, 0.2, 0.3])], "must have 2 values"),
    ],
)
def test_a_damaged_log_is_a_clear_error_not_a_crash_or_a_huge_allocation(
    tmp_path: Path, messages: list[tuple[str, bytes]], says: str
) -> None:
    """``teleop report`` may read logs copied from another host: every field is checked as it is
    read, a tick jump is bounded before anything is allocated, and what is wrong is said."""
    from shell.mcaplog import LogError, iter_ticks

    # A message on another channel ("x") between two closes a chunk: the checks across chunks.
    path = _mcap(
        tmp_path / "operator.mcap", messages, chunk_size=1 if any(t == "x" for t, _ in messages) else 1 << 20
    )
    with pytest.raises(LogError, match=says):
        for _ in iter_ticks(path):
            pass


@pytest.mark.integration  # the log's writer process
def test_teleop_report_on_a_damaged_log_says_what_is_wrong(tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "operator.mcap").write_bytes(b"hello world" * 50)
    _mcap(logs / "teleoperator.mcap", [_sig(0)])
    r = subprocess.run(
        [*TELEOP, "report", str(logs), "--no-sim", "--no-plots"], capture_output=True, text=True
    )
    assert r.returncode == 2 and r.stderr.startswith("teleop: error: cannot build the report: ")
    assert "operator.mcap: not a readable MCAP file (InvalidMagic" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.integration  # the log's writer process
@pytest.mark.parametrize("kind", ["directory", "fifo", "device", "swapped", "transport"])
def test_teleop_report_refuses_what_is_not_a_log_in_one_line(tmp_path: Path, kind: str) -> None:
    """A directory, a FIFO (a read would block) or a device where a log should be is never opened;
    logs of the wrong role, or a transport the stack does not have, are named as such."""
    logs = tmp_path / "logs"
    logs.mkdir()
    _mcap(logs / "teleoperator.mcap", [_sig(0)])
    op = logs / "operator.mcap"
    args: list[str] = []
    if kind == "directory":
        op.mkdir()
    elif kind == "fifo":
        os.mkfifo(op)
    elif kind == "device":
        op.symlink_to("/dev/zero")
    elif kind == "swapped":  # the teleoperator's log under the operator's name: no /operator/summary
        _mcap(op, [_sig(0)])
        (logs / "teleoperator.mcap").rename(tmp_path / "x.mcap")
        op.rename(logs / "teleoperator.mcap")
        (tmp_path / "x.mcap").rename(op)
    else:
        _mcap(op, [_sig(0)])
        args = ["--transport", "nan"]
    r = subprocess.run(
        [*TELEOP, "report", str(logs), "--no-sim", "--no-plots", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    want = {
        "directory": "operator.mcap: not a regular file",
        "fifo": "operator.mcap: not a regular file",
        "device": "operator.mcap: not a regular file",
        "swapped": "has no /operator/summary or /operator/session message",
        "transport": "invalid choice: 'nan'",
    }[kind]
    assert want in lines[0], lines[0]


def test_a_log_cut_before_its_session_began_is_named_as_cut_not_as_a_strangers(tmp_path: Path) -> None:
    """A report of a log cut short said 'not a teleoperator's log' (issue 48): a log that never
    reached its closing magic is named as cut; a finished file without a session is a stranger's."""
    from teleop.offline.logfile import LogError, log_session

    whole = _mcap(tmp_path / "teleoperator.mcap", [("x", b"{}")])
    with pytest.raises(LogError, match="not a teleoperator's log"):
        log_session(whole)
    data = whole.read_bytes()
    whole.write_bytes(data[: len(data) // 2])
    with pytest.raises(LogError, match="was cut short before its session began"):
        log_session(whole)


def test_the_status_line_keeps_within_120_columns_unless_wide() -> None:
    """Status lines ran to 224 characters and wrapped (issue 48); big counts included."""
    from shell.watch import STATUS_COLUMNS, status_line

    op, to = _pair()
    _run(op, to, range(3000))
    for port, role in ((op, "operator"), (to, "teleoperator")):
        port.tx.packets = port.rx.packets = 999_999  # a week's session at a sparse codec's rate
        pv = port.node.passivity
        pv.violations, pv.controller_active_ticks = 99_999, 999_999
        line = status_line(role, port, 2999, 99_999, insecure=True, rtt_ns=50_000)
        assert len(line) <= STATUS_COLUMNS, line
        assert "tx 999999 rx 999999" in line and "watchdog 99999/999999" in line and "INSECURE" in line
        wide = status_line(role, port, 2999, 99_999, insecure=True, rtt_ns=50_000, wide=True)
        assert "violations 99999, controller 999999 ticks" in wide and len(wide) > len(line)
    small = status_line("operator", *_pair()[:1], 10, 0, insecure=False)
    assert len(small) <= STATUS_COLUMNS
