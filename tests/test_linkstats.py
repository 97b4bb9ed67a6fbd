"""LinkObserver on synthetic arrivals: every figure is known exactly in advance."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from teleop.session.link.linkstats import LinkObserver
from teleop.session.link.quantiles import linear_quantile

KEYS = {
    "spec",
    "received",
    "loss",
    "delay_ms",
    "duplicates",
    "reordered",
    "throughput_bps",
    "dropped_by_limit",
}


def test_clean_link_exact_figures() -> None:
    obs = LinkObserver("delay 5ms")
    for k in range(1000):  # 1 kHz, 100 B, 5 ms one-way
        obs.observe(k * 1e-3 + 5e-3, k, k * 1e-3, 100)
    s = obs.summary()
    assert set(s) == KEYS and s["spec"] == "delay 5ms"
    assert s["received"] == 1000 and s["loss"] == 0.0 and s["duplicates"] == s["reordered"] == 0
    assert s["delay_ms"]["mean"] == pytest.approx(5.0) and s["delay_ms"]["p99"] == pytest.approx(5.0)
    assert s["throughput_bps"] == pytest.approx(1000 * 800 / 0.999)  # bits over first..last arrival


def test_loss_duplicates_reordered_counts() -> None:
    obs = LinkObserver()
    # seqs 0..9 sent; 3 and 7 lost; 5 duplicated twice; 2 arrives after 4 (reordered), 6 after 8
    for seq in [0, 1, 4, 2, 5, 5, 8, 6, 5, 9]:
        obs.observe(0.0, seq, 0.0, 10)
    s = obs.summary()
    assert s["received"] == 10
    assert s["duplicates"] == 2  # the late copy of 5 is a duplicate, not a reorder
    assert s["reordered"] == 2
    assert s["loss"] == pytest.approx(2 / 10)


def test_tail_loss_needs_the_senders_count() -> None:
    obs = LinkObserver()
    for seq in range(90):  # 90..99 lost at the tail: invisible without ``sent``
        obs.observe(seq * 1e-3, seq, seq * 1e-3, 10)
    assert obs.summary()["loss"] == 0.0
    assert obs.summary(sent=100)["loss"] == pytest.approx(0.10)
    assert obs.summary(sent=100, dropped_by_limit=4)["dropped_by_limit"] == 4


def test_delay_percentiles() -> None:
    obs = LinkObserver()
    delays = np.arange(1, 101) * 1e-3  # 1..100 ms, arriving out of order of delay
    for k, d in enumerate(np.random.default_rng(0).permutation(delays)):
        obs.observe(1.0 + d, k, 1.0, 50)
    dm = obs.summary()["delay_ms"]
    assert dm["mean"] == pytest.approx(50.5)
    assert dm["p50"] == pytest.approx(50.5) and dm["p99"] == pytest.approx(np.percentile(delays * 1e3, 99))


def test_duplicate_delay_is_not_counted() -> None:
    obs = LinkObserver()
    obs.observe(0.010, 0, 0.0, 10)
    obs.observe(0.500, 0, 0.0, 10)  # a late copy: counted as duplicate, its delay ignored
    assert obs.summary()["delay_ms"]["mean"] == pytest.approx(10.0)


def test_throughput_counts_every_arrival_over_the_span() -> None:
    obs = LinkObserver()
    for k in range(11):  # 11 x 125 B over 1 s, one of them a duplicate
        obs.observe(0.1 * k, min(k, 9), 0.0, 125)
    assert obs.summary()["throughput_bps"] == pytest.approx(11 * 1000 / 1.0)


def test_empty_and_single_arrival() -> None:
    s = LinkObserver().summary()
    assert s["received"] == 0 and s["loss"] == 0.0 and s["throughput_bps"] == 0.0
    assert s["delay_ms"] == {"mean": None, "p50": None, "p99": None}
    assert LinkObserver().summary(sent=5)["loss"] == 1.0
    one = LinkObserver()
    one.observe(1.0, 0, 0.9, 100)
    assert one.summary()["throughput_bps"] == 0.0 and one.summary(sent=1)["loss"] == 0.0


def test_large_and_sparse_sequence_numbers() -> None:
    obs = LinkObserver()
    top = 0xFFFFFFFF
    for seq in [top - 2, top, 5, top - 1, top]:  # memory is per touched chunk, not per max seq
        obs.observe(0.0, seq, 0.0, 1)
    s = obs.summary()
    assert s["duplicates"] == 1 and s["reordered"] == 2
    assert s["loss"] == pytest.approx(1 - 4 / 2**32)
    assert obs.summary(sent=10)["loss"] == pytest.approx(0.9)  # only seqs below ``sent`` count
    assert obs.summary(sent=2**32)["loss"] == pytest.approx(1 - 4 / 2**32)


def test_sent_across_chunk_boundaries() -> None:
    obs = LinkObserver()
    seqs = [s for s in range(0, 200_000) if s % 3]  # every third lost, spanning four chunks
    for s in seqs:
        obs.observe(0.0, s, 0.0, 1)
    for sent in (1, 65_535, 65_536, 65_537, 131_073, 200_000):
        expected = sum(1 for s in range(sent) if s % 3 == 0)
        assert obs.summary(sent=sent)["loss"] == pytest.approx(expected / sent)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False), min_size=1, max_size=300),
    st.floats(0.0, 1.0),
)
@example(xs=[0.0, 1.0], q=0.5)  # gamma exactly 0.5: numpy's lerp from the upper end
@example(xs=[0.1, 0.2, 0.3], q=0.99)
def test_linear_quantile_is_numpys_bit_for_bit(xs: list[float], q: float) -> None:
    """Issue 37: the phase estimator's quantile without ``np.quantile``'s Python overhead (~270 us
    cold in a tick), the same float to the last bit, so teleop sim's goldens do not move."""
    x = np.array(xs)
    want = float(np.quantile(x, q))
    got = linear_quantile(x, q)
    assert got == want or (math.isnan(got) and math.isnan(want)), (got, want)
    np.testing.assert_array_equal(x, np.array(xs))  # the input is not reordered
