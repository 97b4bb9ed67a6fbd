"""The runner's early drain (transport.session._Runner.drain_early): datagrams that arrived before
the spin are fed in the spin's time while each one's expected cost ends before the limit; the rest
wait, in order, for the drain at the deadline.  And its early tick (``_Runner.tick_early``): the
coming tick runs in the spin's time unless that would change what it computes."""

from __future__ import annotations

from typing import Any

from transport.session import EARLY_COST_START_NS, _Runner


class _Clock:
    def __init__(self) -> None:
        self.t = 0

    def __call__(self) -> int:
        return self.t


class _Transport:
    def __init__(self, batches: list[list[tuple[bytes, Any, int]]]) -> None:
        self.batches = batches

    def drain(self) -> list[tuple[bytes, Any, int]]:
        return self.batches.pop(0) if self.batches else []


class _Endpoint:
    """Feeding a datagram costs ``cost`` ns of the fake clock."""

    def __init__(self, clock: _Clock, cost: int) -> None:
        self.clock, self.cost = clock, cost
        self.fed: list[bytes] = []

    def receive_datagram(self, data: bytes, addr: Any, t_rx: int) -> None:
        self.fed.append(data)
        self.clock.t += self.cost


def _runner(batches: list[list[tuple[bytes, Any, int]]], cost: int) -> tuple[Any, _Endpoint]:
    r: Any = object.__new__(_Runner)  # only the drain's state: no socket, log or endpoint to build
    clock = _Clock()
    r.clock, r.tr, r._pending, r._rx_cost_ns = clock, _Transport(batches), [], EARLY_COST_START_NS
    r.ep = _Endpoint(clock, cost)
    return r, r.ep


def test_the_early_drain_stops_before_the_limit_and_the_deadline_drain_feeds_the_rest_in_order() -> None:
    got = [(bytes([i]), ("h", 1), i) for i in range(10)]
    r, ep = _runner([got, [(b"late", ("h", 1), 99)]], cost=20_000)
    r.drain_early(until_ns=100_000)
    early = len(ep.fed)
    assert 1 <= early < 10 and ep.fed == [bytes([i]) for i in range(early)]
    assert ep.clock.t <= 100_000  # none started that its expected cost would carry past the limit
    r.drain()
    assert ep.fed == [bytes([i]) for i in range(10)] + [b"late"] and r._pending == []


def test_after_an_early_tick_what_the_early_drain_left_is_fed_without_another_read() -> None:
    """``feed_pending`` (the wake path after a tick run early): the datagrams the early drain read
    and left, in order, and the socket not read again (what waits there is the next wake's)."""
    got = [(bytes([i]), ("h", 1), i) for i in range(6)]
    r, ep = _runner([got, [(b"next tick's", ("h", 1), 99)]], cost=20_000)
    r.drain_early(until_ns=60_000)
    early = len(ep.fed)
    assert 1 <= early < 6
    r.feed_pending()
    assert ep.fed == [bytes([i]) for i in range(6)] and r._pending == []
    assert r.tr.batches == [[(b"next tick's", ("h", 1), 99)]]  # not read
    r.feed_pending()  # nothing left: a no-op
    assert len(ep.fed) == 6


def test_the_early_drain_learns_the_cost_of_a_datagram() -> None:
    r, ep = _runner([[(b"x", None, 0)] * 50], cost=2_000)
    r.drain_early(until_ns=10**9)
    assert len(ep.fed) == 50 and 2_000 <= r._rx_cost_ns < 3_000
    r, ep = _runner([[(b"x", None, 0)] * 3], cost=1)
    r.drain_early(until_ns=EARLY_COST_START_NS - 1)  # the first guess alone does not fit
    assert ep.fed == [] and len(r._pending) == 3


class _Ticker:
    def __init__(self, k: int, deadline: int) -> None:
        self.k, self.next_deadline = k, deadline


class _TickingEndpoint:
    """What tick_early asks of an endpoint: whether ticks are due, whose session, grace, tick."""

    def __init__(self, grace: bool = False) -> None:
        self.running, self.params, self.grace = True, object(), grace
        self.ticked: list[tuple[int, int]] = []
        self.fed: list[bytes] = []

    def grace_needed(self, k: int) -> bool:
        return self.grace

    def tick(self, k: int, now_ns: int) -> None:
        self.ticked.append((k, now_ns))

    def receive_datagram(self, data: bytes, addr: Any, t_rx: int) -> None:
        self.fed.append(data)
        if data == b"due payload":
            self.grace = False


def _ticking_runner(ep: _TickingEndpoint, now: int, pending: tuple[bytes, ...] = ()) -> Any:
    r: Any = object.__new__(_Runner)
    clock = _Clock()
    clock.t = now
    r.clock, r.ep, r._pending = clock, ep, [(d, ("h", 1), 0) for d in pending]
    return r


def test_the_coming_tick_runs_in_the_spins_time_when_nothing_it_needs_is_missing() -> None:
    ep = _TickingEndpoint()
    r = _ticking_runner(ep, now=900_000)
    assert r.tick_early(_Ticker(7, 1_000_000), ep.params) == 7
    assert ep.ticked == [(7, 900_000)]


def test_the_tick_waits_for_its_deadline_when_early_would_change_it() -> None:
    due_payload_missing = _TickingEndpoint(grace=True)  # grace at the deadline, as before
    replaced = _TickingEndpoint()  # a takeover replaced the session while the loop slept
    ended = _TickingEndpoint()
    ended.running = False
    late = _TickingEndpoint()  # woke at or past the deadline: the tick runs from it, as before
    for ep, session, now in (
        (due_payload_missing, due_payload_missing.params, 900_000),
        (replaced, object(), 900_000),
        (ended, ended.params, 900_000),
        (late, late.params, 1_000_000),
    ):
        r = _ticking_runner(ep, now)
        assert r.tick_early(_Ticker(7, 1_000_000), session) is None
        assert ep.ticked == []


def test_a_due_payload_the_early_drain_left_is_fed_and_the_tick_still_runs_early() -> None:
    """A late wake-up leaves the early drain no budget, so the due payload may wait in ``_pending``:
    tick_early feeds it (in order, with what came before it) rather than send the tick to the
    deadline; a payload still missing after that goes to the deadline's grace, as before."""
    ep = _TickingEndpoint(grace=True)
    r = _ticking_runner(ep, now=900_000, pending=(b"older", b"due payload"))
    assert r.tick_early(_Ticker(7, 1_000_000), ep.params) == 7
    assert ep.fed == [b"older", b"due payload"] and r._pending == [] and ep.ticked == [(7, 900_000)]
    missing = _TickingEndpoint(grace=True)
    r = _ticking_runner(missing, now=900_000, pending=(b"not it",))
    assert r.tick_early(_Ticker(7, 1_000_000), missing.params) is None
    assert missing.fed == [b"not it"] and missing.ticked == []
