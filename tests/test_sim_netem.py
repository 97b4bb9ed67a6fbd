"""``teleop sim`` over impaired links: the receiver-side measurement matches the spec, and every
impairment that only drops, delays, duplicates or reorders packets leaves the channel passive.

Statistical bounds are about 5 sigma on fixed seeds, so they do not flake.  Each check also asserts
passivity (eq. 5 per direction at every tick): the decoders play zero on underrun and the nodes drop
stale packets, so no loss/delay/duplicate/reorder/rate pattern may make energy.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from teleop.offline.sim import ENERGY_TOLERANCE, SimConfig, run_case, run_set
from teleop.session.link.netem import NetemError

N = 5000  # packets per direction: codec none, 5 s at 1 kHz


def run(spec: str, codec: str = "none", seed: int = 0, **kw: Any) -> dict[str, Any]:
    s: dict[str, Any] = run_case(
        SimConfig(codec=codec, netem_forward=spec, netem_backward=spec, seed=seed, **kw)
    ).summary
    return s


def assert_passive(s: dict[str, Any]) -> None:
    assert s["passive"] is True, s["energy"]
    assert s["min_energy_margin"] >= -ENERGY_TOLERANCE, s["energy"]


def within(x: float, p: float, n: int, sigmas: float = 5.0) -> bool:
    return abs(x - p) <= sigmas * math.sqrt(p * (1 - p) / n)


def test_delay_with_jitter_is_observed_with_tick_rounding() -> None:
    s = run("delay 50ms 5ms")
    assert_passive(s)
    for d in ("forward", "backward"):
        link = s["link"][d]
        dm = link["delay_ms"]
        # uniform on [45, 55) ms, taken at the next 1 ms tick: mean 50.5 ms, at most 55 ms; backward
        # from the teleoperator's tick, its phase (under a period) after the packet's t_us
        late = s["latency"]["phase"] if d == "backward" else 0.0
        assert 50.0 <= dm["mean"] - late <= 51.0 and 49.0 <= dm["p50"] - late <= 52.0
        assert dm["mean"] <= dm["p99"] <= 55.0 + late + 1e-6
        assert link["loss"] == 0.0 and link["duplicates"] == 0  # in-flight at the end still counted
        assert link["reordered"] > 0  # netem jitter without rate reorders
        assert link["spec"] == "delay 50ms 5ms"


def test_random_loss_is_observed_within_binomial_bounds() -> None:
    s = run("loss 10%")
    assert_passive(s)
    for d, rx in (("forward", "teleoperator"), ("backward", "operator")):
        link = s["link"][d]
        assert within(link["loss"], 0.10, N)
        # what the node got, plus (backward) the packet sent at the last tick, seen only by the drain
        assert 0 <= link["received"] - s["counters"][rx]["received"] <= (d == "backward")
    assert s["link"]["forward"]["received"] != s["link"]["backward"]["received"]  # independent seeds


def test_duplicates_are_observed_and_dropped_as_replays() -> None:
    s = run("duplicate 20%")
    assert_passive(s)
    for d, rx in (("forward", "teleoperator"), ("backward", "operator")):
        link = s["link"][d]
        assert within(link["duplicates"] / N, 0.20, N)
        assert link["loss"] == 0.0 and link["reordered"] == 0
        # A duplicate carries its original's counter: the replay window drops it before the node.
        assert s["security"][d]["replayed"] == link["duplicates"] and s["counters"][rx]["stale"] == 0


def test_reorder_is_observed() -> None:
    s = run("delay 10ms reorder 25% gap 1", playout="off")
    assert_passive(s)
    for d, rx in (("forward", "teleoperator"), ("backward", "operator")):
        link = s["link"][d]
        assert link["reordered"] > 0 and s["counters"][rx]["stale"] > 0  # overtaken packets not played
        late = s["latency"]["phase"] if d == "backward" else 0.0  # the teleoperator's tick's phase
        assert 7.0 <= link["delay_ms"]["mean"] - late <= 8.0  # 75% at 10 ms, 25% at once
        assert link["delay_ms"]["p50"] == pytest.approx(10.0 + late)


def test_reordered_packets_are_played_in_order_by_the_playout_buffer() -> None:
    """Issue 13: with ``auto`` the overtaken packets wait for their turn instead of being dropped."""
    s = run("delay 10ms reorder 25% gap 1", playout="auto")
    assert_passive(s)
    for d, rx in (("forward", "teleoperator"), ("backward", "operator")):
        assert s["link"][d]["reordered"] > 0
        # Only while the target grows to the reordering depth, in the first ticks: a handful of 5000.
        assert s["counters"][rx]["stale"] <= 10 and s["playout"][d]["late"] <= 10
        assert s["playout"][d]["reordered_fixed"] > 0


def test_rate_limit_gives_the_rate_and_a_growing_queue() -> None:
    s = run("rate 100kbit", duration=1.0)
    assert_passive(s)
    n = 1000
    for d in ("forward", "backward"):
        link = s["link"][d]
        assert link["throughput_bps"] == pytest.approx(100e3, rel=0.02)
        assert link["loss"] == 0.0 and link["dropped_by_limit"] == 0  # the queue stays under 1000
        # offered > rate, so packet k leaves at about (k + 1) tau: its delay grows as k (tau - dt)
        tau = s["directions"][d]["packet_bytes"] / n * 8 / 100e3
        dm = link["delay_ms"]
        assert dm["p50"] == pytest.approx(n / 2 * (tau - 1e-3) * 1e3, rel=0.05)
        assert dm["p99"] > 1.8 * dm["p50"] > 300.0


def test_rate_with_a_short_queue_drops_and_reports_it() -> None:
    s = run("rate 100kbit limit 20", duration=1.0)
    assert_passive(s)
    for d in ("forward", "backward"):
        link = s["link"][d]
        assert link["dropped_by_limit"] > 0
        assert round(link["loss"] * 1000) == link["dropped_by_limit"]  # the only loss there is
        size = s["directions"][d]["packet_bytes"] / s["directions"][d]["packets"]
        queue_ms = 21 * size * 8 / 100e3 * 1e3  # a full queue of 20 packets at 100 kbit/s, plus its own
        assert link["delay_ms"]["p99"] < queue_ms + 1.0  # plus tick rounding


@pytest.mark.parametrize("codec", ["none", "ids:2", "ids:50", "eds:2", "eds:50", "cq:8"])
@pytest.mark.parametrize(
    "spec",
    ["delay 50ms 5ms", "loss 10%", "duplicate 20%", "delay 10ms reorder 25% gap 1", "rate 100kbit"],
)
def test_every_codec_stays_passive_under_impairment(codec: str, spec: str) -> None:
    """With the passivity controller off, passivity must come from the decoders alone (zero on
    underrun, stale packets dropped), not from energy being clipped."""
    s = run(spec, codec=codec, seed=7, duration=1.5, dof=2, controller=False, on_loss="zero")
    assert_passive(s)
    for d in ("forward", "backward"):
        assert s["passivity"][d]["violations"] == 0  # the watchdog agrees: nothing to clip


def test_same_seed_same_results_different_seed_different_results() -> None:
    spec = "delay 10ms 5ms loss 5% duplicate 5%"
    a, b, c = (
        run_case(SimConfig(netem_forward=spec, netem_backward=spec, seed=k, duration=1.0)) for k in (3, 3, 4)
    )
    assert json.dumps(a.summary) == json.dumps(b.summary)
    assert np.array_equal(a.trace.v_hsi, b.trace.v_hsi) and np.array_equal(a.trace.f_to, b.trace.f_to)
    assert a.summary["link"] != c.summary["link"]
    assert not np.array_equal(a.trace.f_hsi, c.trace.f_hsi)


def test_spec_replaces_delay_only_for_its_direction() -> None:
    s = run_case(SimConfig(delay_ms=30, netem_forward="delay 5ms", duration=0.5)).summary
    assert s["link"]["forward"]["delay_ms"]["p50"] == pytest.approx(5.0, abs=0.01)
    # backward from the teleoperator's tick, its phase after the packet's t_us
    assert s["link"]["backward"]["delay_ms"]["p50"] == pytest.approx(30.0 + s["latency"]["phase"], abs=0.01)
    assert s["link"]["backward"]["spec"] == ""


def test_trace_link_in_the_sim(tmp_path: Path) -> None:
    f = tmp_path / "1ms.trace"
    f.write_text("1\n")  # one 1504 B opportunity per ms: each packet leaves at the next ms
    s = run(f"trace {f}", duration=0.5)
    assert_passive(s)
    assert s["link"]["forward"]["delay_ms"]["p99"] == pytest.approx(1.0, abs=0.01)
    assert s["link"]["forward"]["loss"] == 0.0


def test_results_document_and_bad_spec() -> None:
    doc, _ = run_set(["none"], SimConfig(netem_forward="loss 1%", seed=5, duration=0.2))
    assert doc["netem"] == {"forward": "loss 1%", "backward": ""} and doc["seed"] == 5
    assert set(doc["cases"][0]["link"]) == {"forward", "backward"}
    with pytest.raises(NetemError, match="'bogus'") as e:
        run_case(SimConfig(netem_backward="delay 5ms bogus", duration=0.1))
    assert isinstance(e.value, ValueError)
