"""bench.flood's wiring, without a flood: the Zenoh oversize class reaches a real subscriber and is
refused there by length; a run records a baseline per transport and the new fields; the docs table
reads both the new and the old file.  (The floods themselves belong to the benchmark.)"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import time
from pathlib import Path
from typing import Any

import pytest

from bench import flood, tables
from teleop.session import wire
from tests.waiting import await_for, wait_for
from transport.zenoh import ZENOH_PEER, ZenohTransport, make_config


def test_the_zenoh_class_runs_its_sessions_over_zenoh() -> None:
    assert "zenoh_oversize" in flood.CLASSES and "zenoh_oversize" not in flood.UDP_CLASSES
    to = flood._transport_args("zenoh", "teleoperator", 7447)
    op = flood._transport_args("zenoh", "operator", 7447)
    assert to[:4] == op[:4] == ["--transport", "zenoh", "--zenoh-prefix", flood.ZENOH_PREFIX]
    assert to[4:] == ["--zenoh-listen", "tcp/127.0.0.1:7447"]
    assert op[4:] == ["--zenoh-connect", "tcp/127.0.0.1:7447"]
    assert flood._transport_args("udp", "operator", 9)[:2] == ["--peer", "127.0.0.1:9"]


async def test_the_zenoh_flood_publishes_oversize_samples_on_the_session_key() -> None:
    """The stranger's samples arrive at a teleoperator's subscriber on the bench's prefix and are
    refused by length there (a session's bound), never queued."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    to = await ZenohTransport.open(
        "teleoperator", flood.ZENOH_PREFIX, make_config("peer", listen=[f"tcp/127.0.0.1:{port}"])
    )
    try:
        to.max_datagram = wire.max_session_datagram_bytes(2)
        sent = await asyncio.to_thread(flood._zenoh_flood, port, 200.0, 1.5)
        await await_for(lambda: to.oversize, 5.0, "the first oversize sample")
        assert sent > 100 and 0 < to.oversize <= sent
        assert to.drain() == [] and ZENOH_PEER == ("zenoh", 0)
    finally:
        to.close()


def _fake_session(calls: list[tuple[Any, ...]]) -> Any:
    def session(
        key_file: str,
        psk: bytes,
        kind: str | None,
        rate: float,
        duration: float,
        transport: str = "udp",
        rcvbuf_kib: int | None = None,
        pin: bool = False,
        sink: bool = False,
    ) -> dict[str, Any]:
        calls.append((kind, transport, rcvbuf_kib) + (("sink",) if sink else ()))
        udp = transport == "udp"
        return {
            "class": kind or ("baseline" if udp else "baseline_zenoh"),
            "transport": transport,
            "rate": rate if kind else 0,
            "sent": int(rate * (duration - 2)),
            "flood_s": duration - 2 if kind else 0.0,
            "completed": True,
            "lateness_p99_us": 30.0 if sink else 20.0,
            "cpu_fraction": 0.25 if kind else 0.2,
            "overruns": 0,
            "link_lost_events": 0,
            "min_margin_J": 0.0,
            "log_dropped_chunks": 0,
            "oversize_refused": 0,
            "handshake_throttled": 0,
            "transport_oversize": 7 if kind in ("zenoh_oversize", "big_session") else 0,
            "kernel_drops": 0 if udp else None,
            "rcvbuf_errors": 0,
            "rcvbuf_asked": 1024 * rcvbuf_kib if udp and rcvbuf_kib else None,
            "rcvbuf_bytes": 2048 * rcvbuf_kib if udp and rcvbuf_kib else None,
        }

    return session


def test_a_run_records_a_baseline_per_transport_and_the_table_reads_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[tuple[Any, ...]] = []
    monkeypatch.setattr(flood, "session", _fake_session(calls))
    monkeypatch.setattr("bench.commit", lambda root=None: "abc1234")  # no git process in a fast test
    out = tmp_path / "flood.json"
    argv = ["--classes", "big_session", "zenoh_oversize", "--rates", "1000", "--duration", "4"]
    assert flood.main([*argv, "--udp-rcvbuf", "8192", "--out", str(out)]) == 0
    assert calls == [  # a baseline before each transport's floods and after each class
        (None, "udp", 8192),
        ("big_session", "udp", 8192),
        (None, "udp", 8192),
        (None, "zenoh", 8192),
        ("zenoh_oversize", "zenoh", 8192),
        (None, "zenoh", 8192),
    ]
    doc = json.loads(out.read_text())
    assert set(doc["baselines"]) == {"udp", "zenoh"} and doc["baseline"]["transport"] == "udp"
    assert doc["baseline"]["runs"] == 2 and doc["baseline"]["lateness_p99_us_runs"] == [20.0, 20.0]
    assert doc["udp_rcvbuf_kib"] == 8192 and doc["cases_run"] == doc["targets_met"] == 2
    monkeypatch.setattr(tables, "RESULTS", tmp_path)
    md = tables.flood().markdown()
    zenoh_row = next(ln for ln in md.splitlines() if ln.startswith("| zenoh_oversize"))
    assert "| - | 7 |" in zenoh_row  # no kernel drops to read over TCP; refused by length: 7
    assert zenoh_row.startswith("| zenoh_oversize | 1000 | 1000 |")  # reached: sent / flood_s
    assert "baseline (zenoh)" in md


def test_the_table_still_reads_the_file_of_the_last_run() -> None:
    """bench/results/flood.json predates the new fields (one baseline, no Zenoh): same table."""
    assert "baseline" in tables.flood().markdown()


def _busy(seconds: float) -> None:
    """A sender that takes ``seconds`` a datagram (on the CPU: a slow sender, not a sleeping one)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pass


def test_the_flood_is_bounded_in_count_and_time() -> None:
    """_paced calls ``send`` at most at the rate asked, for the time asked, then stops; a sender
    slower than the rate still stops on time (its backlog is not sent in one batch)."""
    seen: list[int] = []
    n = flood._paced(seen.append, 2000.0, 0.2)
    assert 0 < n <= 400 and seen == list(range(n))
    t0 = time.monotonic()
    n = flood._paced(lambda i: _busy(0.001), 1e6, 0.2)  # 1000/s at most, asked 1M/s
    assert time.monotonic() - t0 < 0.35 and n < 300


def test_the_reference_is_the_median_of_the_baselines() -> None:
    runs = [
        {"lateness_p99_us": p, "link_lost_events": 0, "log_dropped_chunks": d, "transport": "udp"}
        for p, d in ((7.0, 0), (215.0, 1), (50.0, 0))
    ]
    ref = flood._reference(runs)
    assert ref["lateness_p99_us"] == 50.0 and ref["lateness_p99_us_runs"] == [7.0, 215.0, 50.0]
    assert ref["runs"] == 3 and ref["log_dropped_chunks"] == 1  # the worst run's, not the first's


def test_a_case_of_several_runs_is_its_median_run_and_the_worst_of_what_must_hold() -> None:
    runs = [
        {
            "lateness_p99_us": p,
            "link_lost_events": ll,
            "log_dropped_chunks": 0,
            "min_margin_J": m,
            "completed": True,
        }
        for p, ll, m in ((300.0, 0, 0.0), (90.0, 1, 0.0), (120.0, 0, -1.0))
    ]
    c = flood._combine(runs)
    assert c["lateness_p99_us"] == 120.0 and c["lateness_p99_us_runs"] == [300.0, 90.0, 120.0]
    assert c["link_lost_events"] == 1 and c["min_margin_J"] == -1.0 and c["completed"]


def test_the_control_runs_each_udp_case_into_a_sink(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[Any, ...]] = []
    monkeypatch.setattr(flood, "session", _fake_session(calls))
    monkeypatch.setattr("bench.commit", lambda root=None: "abc1234")  # no git process in a fast test
    out = tmp_path / "flood.json"
    argv = ["--classes", "random", "--rates", "1000", "--duration", "4", "--repeats", "2", "--control"]
    assert flood.main([*argv, "--out", str(out)]) == 0
    assert calls.count(("random", "udp", None, "sink")) == 2 and calls.count(("random", "udp", None)) == 2
    case = json.loads(out.read_text())["cases"][0]
    assert case["control_p99_us"] == 30.0 and case["control_p99_us_runs"] == [30.0, 30.0]
    assert case["p99_ratio_control"] == pytest.approx(20.0 / 30.0) and case["p99_ratio"] == 1.0
    assert case["cpu_fraction"] == 0.25 and case["cpu_ratio"] == pytest.approx(1.25)


class _Value:
    value: float = 0


@pytest.mark.parametrize("sink", [False, True])
def test_the_control_flood_reaches_no_one(sink: bool) -> None:
    """Into the sink the same datagrams leave at the same rate and never reach the target port."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as target:
        target.bind(("127.0.0.1", 0))
        target.setblocking(False)
        sent, secs = _Value(), _Value()
        now = time.monotonic()
        port = target.getsockname()[1]
        flood.flood(port, "random", [b"x" * 100], 2000.0, now, now + 0.2, sent, secs, sink=sink)
        got: list[bytes] = []

        def read() -> bool:
            with contextlib.suppress(BlockingIOError):
                while True:
                    got.append(target.recv(2048))
            return b"end" in got

        # What is queued (a full buffer drops the rest), then a marker of our own behind the flood's
        # last datagram: once it is read, whatever the flood sent here has arrived (loopback keeps a
        # host's datagrams to one port in order).
        read()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as marker:
            marker.sendto(b"end", ("127.0.0.1", port))
        wait_for(read, 5.0, "the marker after the flood")
        got.remove(b"end")
        assert sent.value > 100
        assert len(got) == 0 if sink else len(got) > 100  # (at most what its receive buffer holds)
