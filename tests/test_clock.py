"""Issue 37 item 1 and issue 35 item 4 in virtual time: the teleoperator ticks when the operator's
packet is due, and a clock a handshake-only delayer skewed is put right in session (tests/vnet.py).
"""

from __future__ import annotations

from typing import Any

import pytest

from teleop.session.endpoint import ClockShifted, SessionEnded, State
from teleop.session.link.phase import latency
from teleop.session.summary import SessionSummary

from .vnet import MS, OP, TO, VirtualNet, params

TO_OFFSET = 5_000_000_000


def ended(h: Any) -> dict[str, Any]:
    (ev,) = h.of(SessionEnded)[-1:]
    return SessionSummary(ev.summary).document()


def run(net: VirtualNet, **kw: Any) -> tuple[Any, Any]:
    to = net.teleoperator(offset_ns=TO_OFFSET)
    op = net.operator(params(codec="none", duration=2.0, **kw))
    net.seconds(30.0, stop=lambda: op.ep.finished and to.ep.finished)
    return op, to


def lat(op: Any, to: Any) -> dict[str, Any]:
    o, t = (h.of(SessionEnded)[-1].summary.port for h in (op, to))
    pl = {"forward": t["playout"], "backward": o["playout"]}
    return latency(pl, {"forward": t["clock"], "backward": o["clock"]}, 1e-3)


@pytest.mark.parametrize(("one_way_ms", "round_trip_ms"), [(0.1, 1.0), (10.0, 21.0), (10.6, 22.0)])
def test_the_round_trip_is_the_floor_of_the_link(one_way_ms: float, round_trip_ms: float) -> None:
    """Each payload is played at the first tick after it arrives: the round trip is the smallest whole
    number of ticks not below the link's plus the processing margin (1 tick on a quiet loopback)."""
    op, to = run(VirtualNet(one_way_ms))
    lt = lat(op, to)
    assert lt["round_trip"]["p50"] == pytest.approx(round_trip_ms)
    assert lt["round_trip"]["p99"] <= round_trip_ms + 1
    assert lt["floor_ms"] == pytest.approx(round_trip_ms)
    assert 0.1 <= lt["phase"] <= 0.9


def test_a_handshake_only_delayer_costs_at_most_a_tick_of_misplacement() -> None:
    """200 ms added to robot -> operator during the handshake only: the offset is 100 ms off, so the
    robot's tick 0 lands 100 ms early.  In session the operator sees its robot's packets arrive before
    they were sent, moves its own tick 0 to match (skipping those ticks), and no one-way delay it
    reports is negative; the two ends' tick 0 end up within a tick of each other."""
    net = VirtualNet(0.1)
    to = net.teleoperator(offset_ns=TO_OFFSET)
    op = net.operator(params(codec="none", duration=2.0))

    def delayer(now: int, src: Any, dst: Any, data: bytes) -> list[Any]:
        if src == TO and dst == OP and op.ep.state != State.RUNNING:
            net.inject(src, dst, data, 200 * MS)
            return []
        return [(src, dst, data)]

    net.tap = delayer
    net.seconds(30.0, stop=lambda: op.ep.finished and to.ep.finished)
    (so,) = op.started()
    assert so.rtt_ns >= 200 * MS  # the offset it placed the start with was skewed by ~100 ms
    shifts = op.of(ClockShifted)
    assert shifts and sum(s.ticks for s in shifts) >= 99
    # tick 0 of both, on the network's clock, within a tick of each other after the shift
    misplaced = (to.ep.start_ns - TO_OFFSET) - op.ep.start_ns
    assert abs(misplaced) <= 1 * MS, misplaced / MS
    o, t = ended(op), ended(to)
    assert o["completed"] and t["completed"]
    for h in (op, to):
        assert h.of(SessionEnded)[-1].summary.port["link_received"]["delay_ms"]["p50"] >= 0
    lt = lat(op, to)
    assert lt["round_trip"]["p50"] == pytest.approx(1.0)
