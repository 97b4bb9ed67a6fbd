"""netem link model: statistics against netem's semantics, the parser's errors, the trace link.

Statistical checks use fixed seeds and bounds of about 5 sigma, so they do not flake, yet a model with
the wrong semantics (wrong defaults, wrong state machine, wrong reorder gap) lands far outside them.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter, deque
from collections.abc import Iterable
from pathlib import Path
from statistics import NormalDist

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop.session.link.netem import (
    PACKET_SIZE,
    FourStateModel,
    GEModel,
    Link,
    NetemError,
    NetemLink,
    NetemSpec,
    TraceLink,
    load_trace,
    make_link,
    parse_netem,
)

MS = 1e-3


def payload(seq: int, size: int = 16) -> bytes:
    return seq.to_bytes(4, "big") + bytes(max(0, size - 4))


def seq_of(data: bytes) -> int:
    return int.from_bytes(data[:4], "big")


def run(link: Link, sends: Iterable[tuple[float, bytes]]) -> list[tuple[float, bytes]]:
    """Send in time order, collecting every delivery at its exact time (as a virtual-time runner would)."""
    out: list[tuple[float, bytes]] = []

    def drain(until: float) -> None:
        while (t := link.next_due()) is not None and t <= until:
            out.extend((t, d) for d in link.due(t))

    for now, data in sends:
        drain(now)
        link.send(now, data)
    drain(math.inf)
    return out


def periodic(n: int, dt: float = MS, size: int = 16) -> list[tuple[float, bytes]]:
    return [(k * dt, payload(k, size)) for k in range(n)]


def link(spec: str, seed: int = 1) -> NetemLink:
    return NetemLink(parse_netem(spec), seed)


def loss_pattern(spec: str, n: int, seed: int = 1) -> np.ndarray:
    """True where packet k was lost, on a link with no delay."""
    lk = link(spec, seed)
    lost = []
    for k in range(n):
        lk.send(k * MS, b"x")
        lost.append(not lk.due(k * MS))
    return np.array(lost)


def bursts(lost: np.ndarray) -> list[int]:
    """Lengths of the runs of consecutive losses."""
    out, run_len = [], 0
    for x in lost:
        if x:
            run_len += 1
        elif run_len:
            out.append(run_len)
            run_len = 0
    return out


def latencies(spec: str, n: int = 20000, seed: int = 1) -> np.ndarray:
    got = run(link(spec, seed), periodic(n))
    return np.array([t - seq_of(d) * MS for t, d in got])


# --- loss -------------------------------------------------------------------------------------------


def test_random_loss_rate_within_binomial_bounds() -> None:
    n, p = 20000, 0.05
    lk = link("loss 5%", seed=3)
    got = run(lk, periodic(n))
    assert abs(lk.stats.lost - n * p) < 5 * math.sqrt(n * p * (1 - p))
    assert len(got) == lk.stats.delivered == n - lk.stats.lost


def test_loss_correlation_clusters_losses_and_lowers_the_rate_as_in_netem() -> None:
    """netem's get_crandom is known to be weak: the rate falls well below the nominal one."""
    lost = loss_pattern("loss 30% 25%", 20000)
    rate = lost.mean()
    assert 0.15 < rate < 0.27
    assert lost[1:][lost[:-1]].mean() > 1.25 * rate  # P(loss | previous lost) > P(loss)


def test_gilbert_elliott_rate_and_mean_burst_length() -> None:
    """Simple Gilbert (1-h = 100%, 1-k = 0%): rate p / (p + r), bursts geometric with mean 1/r."""
    p, r = 0.05, 0.25
    lost = loss_pattern("loss gemodel 5% 25%", 60000)
    assert lost.mean() == pytest.approx(p / (p + r), abs=0.013)
    assert np.mean(bursts(lost)) == pytest.approx(1 / r, abs=0.35)


def test_gilbert_elliott_default_r_is_one_minus_p_so_p_alone_is_bernoulli() -> None:
    """iproute2 >= 5.2 (r = 1 - p); the older r = 100% default would give 0.3 / 1.3 = 23%."""
    lost = loss_pattern("loss gemodel 30%", 20000)
    assert abs(lost.mean() - 0.3) < 5 * math.sqrt(0.3 * 0.7 / 20000)
    assert np.mean(bursts(lost)) == pytest.approx(1 / 0.7, abs=0.05)


def test_gilbert_elliott_loss_in_both_states() -> None:
    """1-h = 50% in the bad state, 1-k = 2% in the good one: 1/6 * .5 + 5/6 * .02 = 0.1."""
    lost = loss_pattern("loss gemodel 5% 25% 50% 2%", 60000)
    assert lost.mean() == pytest.approx(0.1, abs=0.01)


def test_four_state_loss_rate_is_the_stationary_probability_of_states_3_and_4() -> None:
    p13, p31, p32, p23, p14 = 0.05, 0.30, 0.10, 0.20, 0.02
    trans = np.array(
        [
            [1 - p13 - p14, 0, p13, p14],
            [0, 1 - p23, p23, 0],
            [p31, p32, 1 - p31 - p32, 0],
            [1, 0, 0, 0],
        ]
    )
    w, v = np.linalg.eig(trans.T)
    pi = np.real(v[:, np.argmin(abs(w - 1))])
    pi /= pi.sum()
    lost = loss_pattern("loss state 5% 30% 10% 20% 2%", 60000)
    assert lost.mean() == pytest.approx(pi[2] + pi[3], abs=0.01)


def test_four_state_defaults_make_p13_alone_bernoulli() -> None:
    lost = loss_pattern("loss state 10%", 20000)
    assert abs(lost.mean() - 0.1) < 5 * math.sqrt(0.1 * 0.9 / 20000)


def test_duplicate_and_loss_on_one_packet_cancel_as_in_the_kernel() -> None:
    """netem_enqueue: count = 1 + dup - loss, so 100% of each still delivers every packet once."""
    lk = link("duplicate 100% loss 100%")
    got = run(lk, periodic(1000))
    assert [seq_of(d) for _, d in got] == list(range(1000))
    assert lk.stats.lost == lk.stats.duplicated == 0


# --- delay and jitter -----------------------------------------------------------------------------


def _oracle(dist: str, m: int = 20000) -> tuple[float, float]:
    """Mean and std, in units of jitter, of iproute2's table formulas taken as continuous quantiles."""
    inv = NormalDist().inv_cdf
    q = (np.arange(m) + 0.5) / m
    normal = np.array([inv(x) for x in q])
    pareto = np.minimum((((1 - q) ** (-1 / 3)) - 1.5) * 4 / 3, 32767 / 8192)
    v = {"normal": normal, "pareto": pareto, "paretonormal": (normal + 3 * pareto) / 4}[dist]
    return float(v.mean()), float(v.std())


def test_uniform_jitter_is_the_default_mean_delay_std_jitter_over_sqrt3() -> None:
    lat = latencies("delay 50ms 10ms")
    assert lat.mean() == pytest.approx(50 * MS, abs=0.25 * MS)
    assert lat.std() == pytest.approx(10 * MS / math.sqrt(3), rel=0.03)
    assert lat.min() >= 40 * MS - 1e-12 and lat.max() < 60 * MS


@pytest.mark.parametrize("dist", ["normal", "pareto", "paretonormal"])
def test_table_distributions_match_netem_tables(dist: str) -> None:
    mean, std = _oracle(dist)
    lat = latencies(f"delay 50ms 10ms distribution {dist}")
    assert lat.mean() == pytest.approx(50 * MS + mean * 10 * MS, abs=0.4 * MS)
    assert lat.std() == pytest.approx(std * 10 * MS, rel=0.04)
    if dist == "pareto":  # heavy right tail, floor at (1 - 1.5) * 4/3 jitter below the delay
        assert lat.min() >= 50 * MS - 10 * MS * 2 / 3 - 1e-9
        assert np.median(lat) < lat.mean()


def test_uniform_distribution_keyword_is_the_default() -> None:
    default = latencies("delay 50ms 10ms", 500)
    assert np.array_equal(default, latencies("delay 50ms 10ms distribution uniform", 500))


def test_negative_delays_are_clamped_to_zero() -> None:
    lat = latencies("delay 1ms 5ms", 2000)
    assert lat.min() == 0.0 and (lat == 0).mean() > 0.3


def test_jitter_reorders_without_rate() -> None:
    got = run(link("delay 50ms 20ms"), periodic(2000))
    seqs = [seq_of(d) for _, d in got]
    overtaken = sum(1 for a, b in itertools.pairwise(seqs) if b < a)
    assert overtaken > 200


@pytest.mark.parametrize("dist", ["uniform", "normal", "pareto"])
def test_jitter_never_reorders_with_rate(dist: str) -> None:
    got = run(link(f"delay 50ms 20ms distribution {dist} rate 100mbit"), periodic(2000))
    assert [seq_of(d) for _, d in got] == list(range(2000))
    lat = np.array([t - seq_of(d) * MS for t, d in got])
    assert lat.std() > 2 * MS  # jitter is still there, it just cannot overtake


# --- reorder --------------------------------------------------------------------------------------


def test_reorder_gap_1_sends_p_of_packets_at_once_and_they_overtake() -> None:
    n = 20000
    lk = link("delay 10ms reorder 25%")
    got = run(lk, periodic(n))
    assert abs(lk.stats.reordered - n * 0.25) < 5 * math.sqrt(n * 0.25 * 0.75)
    lat = np.array([t - seq_of(d) * MS for t, d in got])
    at_once = np.abs(lat) < 1e-9  # the runner tags packets due within 1e-9 with one time
    assert int(at_once.sum()) == lk.stats.reordered
    assert np.all(at_once | (np.abs(lat - 10 * MS) < 1e-9))
    seqs = [seq_of(d) for _, d in got]
    overtaking = sum(1 for i, s in enumerate(seqs) if i and s < max(seqs[:i][-20:]))
    assert overtaking > 0.9 * n * 0.25 * 0.9  # nearly every zero-delay packet passes its delayed elders


def test_reorder_gap_keeps_n_minus_1_delayed_packets_between_reorders() -> None:
    """gap 5: 4 forced delays, then tries with p = .25 (mean 4): one reorder per 8 packets."""
    n = 20000
    lk = link("delay 10ms reorder 25% gap 5")
    got = run(lk, periodic(n))
    assert abs(lk.stats.reordered - n / 8) < 110  # renewal count: sd ~ sqrt(n * 12 / 8**3) = 22
    immediate = sorted(seq_of(d) for t, d in got if abs(t - seq_of(d) * MS) < 1e-9)
    assert immediate[0] >= 4
    assert min(np.diff(immediate)) >= 5


def test_reorder_correlation_and_zero_probability() -> None:
    assert link("delay 10ms reorder 0%").spec.gap == 0
    lk = link("delay 10ms reorder 0%")
    run(lk, periodic(1000))
    assert lk.stats.reordered == 0


# --- rate, limit ----------------------------------------------------------------------------------


def test_rate_cap_throughput_and_linear_queueing_delay() -> None:
    """1000 B every 4 ms (2 Mbit/s) into 1 Mbit/s: 8 ms each out, queueing delay grows 1 s per s."""
    n = 500
    got = run(link("rate 1mbit"), periodic(n, dt=4 * MS, size=1000))
    t = np.array([x for x, _ in got])
    assert [seq_of(d) for _, d in got] == list(range(n))
    assert (n - 1) * 8000 / (t[-1] - t[0]) == pytest.approx(1e6, rel=1e-9)
    sent = np.arange(n) * 4 * MS
    slope, intercept = np.polyfit(sent, t - sent, 1)
    assert slope == pytest.approx(1.0, rel=1e-6)
    assert intercept == pytest.approx(8 * MS, abs=1e-9)


@pytest.mark.parametrize(
    ("spec", "per_packet"),
    [
        ("rate 125kbps", 8 * MS),  # kbps is kilo*bytes*/s, as in tc
        ("rate 1mbit 24", 1024 * 8 / 1e6),
        ("rate 1mbit 0 100 10", 10 * 110 * 8 / 1e6),  # 10 cells of 100 B, 10 B overhead each
    ],
)
def test_rate_units_overhead_and_cells(spec: str, per_packet: float) -> None:
    got = run(link(spec), [(0.0, payload(k, 1000)) for k in range(10)])
    assert [t for t, _ in got] == pytest.approx([per_packet * (k + 1) for k in range(10)])


def test_rate_with_delay_serialises_from_the_last_departure() -> None:
    got = run(link("delay 20ms rate 1mbit"), [(0.0, payload(0, 1000)), (0.001, payload(1, 1000))])
    assert [t for t, _ in got] == pytest.approx([28 * MS, 36 * MS])
    got = run(link("delay 20ms rate 1mbit"), [(0.0, payload(0, 1000)), (0.05, payload(1, 1000))])
    assert [t for t, _ in got] == pytest.approx([28 * MS, 78 * MS])  # queue idle again: no carry-over


def test_tail_drop_at_limit() -> None:
    lk = link("delay 100ms limit 10")
    for k in range(15):
        lk.send(0.0, payload(k))
    assert lk.stats.dropped_by_limit == 5 and lk.in_flight == 10
    lk.send(0.05, payload(15))
    assert lk.stats.dropped_by_limit == 6
    assert [seq_of(d) for d in lk.due(0.1)] == list(range(10))
    lk.send(0.1, payload(16))
    assert lk.stats.dropped_by_limit == 6 and lk.next_due() == pytest.approx(0.2)


def test_limit_counts_packets_not_yet_due_whether_or_not_collected() -> None:
    lk = link("delay 1ms limit 10")
    for k in range(10):
        lk.send(0.0, payload(k))
    lk.send(0.002, payload(10))  # the 10 are due (uncollected), so the queue has room
    assert lk.stats.dropped_by_limit == 0
    assert [seq_of(d) for d in lk.due(0.003)] == list(range(11))


# --- duplicate, corrupt ---------------------------------------------------------------------------


def test_duplicate_rate_and_copies_are_identical() -> None:
    n = 20000
    lk = link("duplicate 10%", seed=5)
    got = run(lk, periodic(n))
    assert abs(lk.stats.duplicated - n * 0.1) < 5 * math.sqrt(n * 0.1 * 0.9)
    assert len(got) == lk.stats.delivered == n + lk.stats.duplicated
    counts = Counter(d for _, d in got)
    assert set(counts.values()) == {1, 2}
    assert sum(c == 2 for c in counts.values()) == lk.stats.duplicated


def test_corrupt_flips_exactly_one_bit() -> None:
    rng = np.random.default_rng(0)
    sends = [(k * MS, payload(k) + rng.bytes(60)) for k in range(2000)]
    lk = link("corrupt 100%")
    got = run(lk, sends)
    assert lk.stats.corrupted == 2000
    for (_, sent), (_, recv) in zip(sends, got, strict=True):
        flipped = sum(bin(a ^ b).count("1") for a, b in zip(sent, recv, strict=True))
        assert flipped == 1 and len(recv) == len(sent)


def test_corrupt_rate_and_empty_packets() -> None:
    lk = link("corrupt 10%")
    run(lk, periodic(20000))
    assert abs(lk.stats.corrupted - 2000) < 5 * math.sqrt(20000 * 0.1 * 0.9)
    lk = link("corrupt 100%")
    assert run(lk, [(0.0, b"")]) == [(0.0, b"")] and lk.stats.corrupted == 0


# --- determinism ----------------------------------------------------------------------------------

BUSY = (
    "delay 20ms 5ms 25% distribution normal loss gemodel 2% 20% duplicate 5% reorder 10% "
    "corrupt 5% rate 10mbit"
)


def test_same_seed_same_trace_different_seed_different_trace() -> None:
    a = run(link(BUSY, 1), periodic(3000, size=64))
    assert a == run(link(BUSY, 1), periodic(3000, size=64))
    assert a != run(link(BUSY, 2), periodic(3000, size=64))


def test_spec_seed_overrides_constructor_seed() -> None:
    a = run(link("loss 50% seed 7", 1), periodic(500))
    assert a == run(link("loss 50% seed 7", 2), periodic(500))
    assert a != run(link("loss 50% seed 8", 1), periodic(500))


def test_no_seed_means_seed_zero() -> None:
    spec = parse_netem("loss 50%")
    assert run(NetemLink(spec), periodic(500)) == run(NetemLink(spec, 0), periodic(500))


SPECS = [
    "",
    "delay 5ms 3ms",
    "delay 5ms 3ms 50% distribution pareto loss 10% 30%",
    "delay 2ms reorder 30% 20% gap 3 duplicate 20% limit 20",
    "delay 1ms 1ms rate 1mbit 20 limit 5 loss state 5% 40% 10% 30% 1%",
    "duplicate 50% 10% corrupt 20% loss gemodel 10% 30% 80% 1%",
]


@settings(max_examples=60, deadline=None)
@given(
    spec=st.sampled_from(SPECS),
    seed=st.integers(0, 2**32),
    steps=st.lists(
        st.tuples(st.floats(0, 0.004), st.integers(0, 1500), st.booleans()), min_size=1, max_size=120
    ),
)
def test_conservation_and_due_contract(spec: str, seed: int, steps: list[tuple[float, int, bool]]) -> None:
    lk = link(spec, seed)
    now, delivered = 0.0, 0
    for dt, size, poll in steps:
        now += dt
        lk.send(now, bytes(size))
        if poll:
            before = lk.next_due()
            got = lk.due(now)
            delivered += len(got)
            assert bool(got) == (before is not None and before <= now + 1e-9)
            nxt = lk.next_due()
            assert nxt is None or nxt > now + 1e-9
        s = lk.stats
        assert s.sent + s.duplicated == s.delivered + s.lost + s.dropped_by_limit + lk.in_flight
    while (t := lk.next_due()) is not None:
        assert t >= now - 1e-9 or lk.in_flight
        delivered += len(lk.due(t))
    assert delivered == lk.stats.delivered and lk.in_flight == 0


# --- parsing --------------------------------------------------------------------------------------


def test_parse_fields_units_and_text() -> None:
    text = "delay 100ms 10ms 25% distribution normal loss random 1% 5% duplicate 2 reorder 3% gap 4 limit 50"
    s = parse_netem(text)
    assert s == NetemSpec(
        text=text,
        delay=0.1,
        jitter=0.01,
        delay_corr=0.25,
        distribution="normal",
        loss=0.01,
        loss_corr=0.05,
        duplicate=0.02,
        reorder=0.03,
        gap=4,
        limit=50,
    )
    assert parse_netem("") == NetemSpec()


@pytest.mark.parametrize(
    ("tok", "seconds"),
    [("1s", 1.0), ("2sec", 2.0), ("10ms", 0.01), ("3MSEC", 0.003), ("250us", 250e-6), ("7usec", 7e-6),
     ("1500us", 1.5e-3), ("1e3us", 1e-3), (".5ms", 5e-4), ("100ns", 1e-7), ("0", 0.0)],
)  # fmt: skip
def test_parse_time_units(tok: str, seconds: float) -> None:
    assert parse_netem(f"delay {tok}").delay == pytest.approx(seconds)


@pytest.mark.parametrize("spec", ["delay 50", "delay 10ms 5", "delay 1.5"])
def test_a_time_without_its_unit_is_refused_naming_the_units(spec: str) -> None:
    """tc reads a bare number as microseconds: ``delay 50`` ran a 15 s session at 50 us, silently."""
    with pytest.raises(NetemError, match=r"a time needs its unit \(s, ms, us or ns\)"):
        parse_netem(spec)


@pytest.mark.parametrize(
    ("tok", "bits"),
    [("1mbit", 1e6), ("1Mbit", 1e6), ("2kbit", 2e3), ("1gbit", 1e9), ("8bit", 8.0), ("1kibit", 1024.0),
     ("125kbps", 1e6), ("1mbps", 8e6), ("10bps", 80.0), ("1000", 8000.0)],
)  # fmt: skip
def test_parse_rate_units_bps_is_bytes(tok: str, bits: float) -> None:
    assert parse_netem(f"rate {tok}").rate == pytest.approx(bits)


def test_parse_defaults_of_loss_models_rate_and_reorder() -> None:
    assert parse_netem("loss gemodel 30%").gemodel == GEModel(0.3, 0.7, 1.0, 0.0)
    assert parse_netem("loss gemodel 1% 10% 70% 0.1%").gemodel == GEModel(0.01, 0.1, 0.7, 0.001)
    assert parse_netem("loss state 10%").state_model == FourStateModel(0.1, 0.9, 0.0, 1.0, 0.0)
    assert parse_netem("loss 0.5").loss == 0.005  # bare percentages are percent, as in tc
    assert parse_netem("delay 10ms reorder 25%").gap == 1  # tc sets gap 1
    s = parse_netem("rate 1gbit -20 64 5")
    assert (s.packet_overhead, s.cell_size, s.cell_overhead) == (-20, 64, 5)
    assert parse_netem("seed 42 delay 1ms").seed == 42
    assert parse_netem("delay 1ms").limit == 1000


@pytest.mark.parametrize(
    ("text", "tok", "pos"),
    [
        ("dely 10ms", "dely", 0),
        ("delay", "delay", 0),
        ("delay 10xs", "10xs", 1),
        ("delay ten", "ten", 1),
        ("delay -5ms", "-5ms", 1),
        ("delay 10ms 2ms 150%", "150%", 3),
        ("delay 10ms delay 20ms", "delay", 2),
        ("loss", "loss", 0),
        ("loss 101%", "101%", 1),
        ("loss 5%%", "5%%", 1),
        ("loss bogus 5%", "bogus", 1),
        ("loss random", "random", 1),
        ("loss gemodel", "gemodel", 1),
        ("loss 1% loss 2%", "loss", 2),
        ("loss state 60% 10% 10% 10% 50%", "50%", 6),
        ("loss state 10% 80% 30%", "30%", 4),
        ("duplicate 5% loss 1% duplicate 5%", "duplicate", 4),
        ("corrupt", "corrupt", 0),
        ("rate", "rate", 0),
        ("rate 10furlongs", "10furlongs", 1),
        ("rate 0kbit", "0kbit", 1),
        ("reorder 25%", "reorder", 0),
        ("delay 0ms reorder 25%", "reorder", 2),
        ("delay 10ms gap 5", "gap", 2),
        ("limit x", "x", 1),
        ("limit -1", "-1", 1),
        ("distribution normal", "distribution", 0),
        ("delay 10ms distribution normal", "distribution", 2),
        ("delay 10ms 1ms distribution weird", "weird", 4),
        ("seed abc", "abc", 1),
        ("delay 10ms ecn", "ecn", 2),
    ],
)
def test_parse_errors_name_the_bad_token_and_show_the_grammar(text: str, tok: str, pos: int) -> None:
    with pytest.raises(NetemError) as exc:
        parse_netem(text)
    err = exc.value
    assert isinstance(err, ValueError)
    assert (err.token, err.position) == (tok, pos)
    msg = str(err)
    assert f"bad token {tok!r} at position {pos}" in msg
    assert "delay TIME [JITTER [CORRELATION]]" in msg and "loss gemodel P [R [1-H [1-K]]]" in msg


# --- make_link, trace link ------------------------------------------------------------------------


@pytest.mark.parametrize("spec", ["", None, "   "])
def test_make_link_empty_is_a_zero_delay_passthrough(spec: str | None) -> None:
    lk = make_link(spec, 0)
    lk.send(1.5, b"a")
    assert lk.next_due() == 1.5
    assert lk.due(1.5) == [b"a"] and lk.next_due() is None
    assert lk.stats.sent == lk.stats.delivered == 1


def test_make_link_netem_and_trace(tmp_path: Path) -> None:
    assert isinstance(make_link("delay 10ms", 0), NetemLink)
    f = tmp_path / "link.trace"
    f.write_text("1\n2\n")
    assert isinstance(make_link(f"trace {f}", 0), TraceLink)
    for bad, tok in [("trace", "trace"), (f"trace {f} extra", "extra")]:
        with pytest.raises(NetemError, match=repr(tok)):
            make_link(bad, 0)


def test_load_trace_text_and_file(tmp_path: Path) -> None:
    assert load_trace("1\n1\n3\n5\n") == [1.0, 1.0, 3.0, 5.0]
    f = tmp_path / "t.trace"
    f.write_text("0\n2.5\n\n7\n")
    assert load_trace(f) == load_trace(str(f)) == [0.0, 2.5, 7.0]


@pytest.mark.parametrize(
    ("text", "match"),
    [("3\n2\n", "non-decreasing"), ("0\n0\n", "nonzero"), ("1\nx\n", "'x'"), ("\n\n", "no timestamps"),
     ("-1\n2\n", "finite")],
)  # fmt: skip
def test_load_trace_errors(text: str, match: str) -> None:
    with pytest.raises(NetemError, match=match):
        load_trace(text)


def test_trace_link_follows_opportunities_and_loops() -> None:
    lk = TraceLink([1, 1, 3, 5])
    got = run(lk, [(0.0, payload(k, PACKET_SIZE)) for k in range(8)])  # one full opportunity each
    assert [t for t, _ in got] == pytest.approx([x * MS for x in (1, 1, 3, 5, 6, 6, 8, 10)])
    assert [seq_of(d) for _, d in got] == list(range(8))


def test_trace_link_opportunity_at_arrival_instant_is_gone_and_idle_skips() -> None:
    lk = TraceLink([1, 1, 3, 5], start=0.0)
    got = run(lk, [(0.003, payload(0)), (100.0, payload(1)), (100.0015, payload(2))])
    # payload(2) does not ride the leftover of the 100.001 opportunity: it had passed when it arrived
    assert [t for t, _ in got] == pytest.approx([0.005, 100.001, 100.003])


def test_trace_link_packs_small_packets_into_one_opportunity() -> None:
    lk = TraceLink([1])  # an opportunity every ms
    got = run(lk, [(0.0, payload(k, 40)) for k in range(80)])
    # 37 * 40 = 1480 B fit in the first 1504; the 38th takes the last 24 B and finishes in the second
    times = [round(t / MS) for t, _ in got]
    assert times == [1] * 37 + [2] * 38 + [3] * 5  # the second carries 16 B of the 38th + 37 * 40
    assert [seq_of(d) for _, d in got] == list(range(80))


def test_trace_link_busy_queue_shares_the_leftover_exact_fill_does_not() -> None:
    lk = TraceLink([2], start=0.0)
    got = run(lk, [(0.0, bytes(100)), (0.001, bytes(100)), (0.0015, bytes(1304)), (0.0019, bytes(1))])
    # 100 + 100 + 1304 = 1504 fill the 2 ms opportunity exactly; the 1-byte packet waits for 4 ms
    assert [t for t, _ in got] == pytest.approx([0.002, 0.002, 0.002, 0.004])


def test_trace_link_large_packet_spills_over_opportunities() -> None:
    lk = TraceLink([1, 2, 3, 4])
    got = run(lk, [(0.0, bytes(3000)), (0.0, bytes(100)), (0.0, bytes(1500)), (0.0, bytes(1501))])
    # 3000 = 1504 + 1496 (8 B left at 2 ms); 100 = 8 + 92; 1500 = 1412 + 88; 1501 = 1416 + 85 (at 5 ms)
    assert [t for t, _ in got] == pytest.approx([2 * MS, 3 * MS, 4 * MS, 5 * MS])
    fresh = TraceLink([1], start=0.0)
    assert run(fresh, [(0.0, bytes(3 * PACKET_SIZE + 1))])[0][0] == pytest.approx(4 * MS)  # ceil(len / 1504)


def test_trace_link_capacity_is_1504_bytes_per_opportunity() -> None:
    lk = TraceLink([1])  # an opportunity every ms
    got = run(lk, [(0.0, bytes(1000))] * 1000)
    assert [t for t, _ in got] == pytest.approx(
        [math.ceil(1000 * (k + 1) / PACKET_SIZE) * MS for k in range(1000)]
    )
    assert lk.stats.delivered == 1000 and lk.in_flight == 0


def mahimahi_reference(trace_ms: list[int], sends: list[tuple[int, int]]) -> list[int]:
    """``link_queue.cc``'s ``rationalize`` loop, opportunity by opportunity, in integer microseconds.

    ``sends`` are (arrival us, size) in time order; returns each packet's departure us.  Opportunities
    at or before an arrival are burnt before the packet is queued, as ``read_packet`` does.
    """
    period = trace_ms[-1] * 1000
    queue: deque[list[int]] = deque()  # [index, bytes left]
    out = [-1] * len(sends)
    i = k = 0
    while i < len(sends) or queue:
        c, j = divmod(k, len(trace_ms))
        t = c * period + trace_ms[j] * 1000
        while i < len(sends) and sends[i][0] < t:
            queue.append([i, sends[i][1]])
            i += 1
        budget = PACKET_SIZE
        while budget > 0 and queue:
            pkt = queue[0]
            pkt[1] -= budget
            budget = 0
            if pkt[1] <= 0:
                budget = -pkt[1]
                out[pkt[0]] = t
                queue.popleft()
        k += 1
    return out


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.integers(0, 6), min_size=1, max_size=6).map(lambda d: list(itertools.accumulate(d))),
    st.lists(st.tuples(st.integers(0, 3000), st.integers(4, 4000)), min_size=1, max_size=40),
)
def test_trace_link_matches_mahimahi_rationalize(trace: list[int], gaps_sizes: list[tuple[int, int]]) -> None:
    if trace[-1] == 0:
        trace = [*trace, 1]
    sends, t_us = [], 0
    for gap, size in gaps_sizes:
        t_us += gap
        sends.append((t_us, min(size, PACKET_SIZE)))  # Mahimahi refuses larger packets
    lk = TraceLink(trace, start=0.0)
    got = run(lk, [(t * 1e-6, payload(k, size)) for k, (t, size) in enumerate(sends)])
    assert [seq_of(d) for _, d in got] == list(range(len(sends)))
    assert [t for t, _ in got] == pytest.approx(
        [t * 1e-6 for t in mahimahi_reference(trace, sends)], abs=1e-9
    )
