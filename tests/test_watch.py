"""shell.watch.LogWatch: the log's events say what happened, never a count that went down."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from shell.watch import LogWatch


class _Log:
    live_every, wants_live = 10**9, False

    def __init__(self) -> None:
        self.events: list[tuple[str, str]] = []

    def event(self, t: float, name: str, detail: str) -> None:
        self.events.append((name, detail))


def _port() -> Any:
    return SimpleNamespace(
        node=SimpleNamespace(peer_restarts=0),
        security=SimpleNamespace(rejected=0, replayed=0, last_rejection=""),
    )


def test_a_stall_is_an_event_and_figures_that_start_again_are_not() -> None:
    """The loop's figures start from zero when a session (re)starts: a CI run's log said "-106
    ticks skipped" and "0 so far" at that moment; a count that went down is a new baseline."""
    log, port, w = _Log(), _port(), LogWatch()
    w.tick(log, port, 0, 0.0, overruns=0, skipped=0)  # type: ignore[arg-type]
    w.tick(log, port, 130, 0.13, overruns=1, skipped=106)  # type: ignore[arg-type]
    assert log.events == [
        ("overrun", "tick 130: 1 so far"),
        ("stall", "tick 130: 106 ticks skipped before it"),
    ]
    w.tick(log, port, 131, 0.131, overruns=0, skipped=0)  # type: ignore[arg-type]  # figures started again
    assert len(log.events) == 2
    w.tick(log, port, 140, 0.14, overruns=0, skipped=5)  # type: ignore[arg-type]
    assert log.events[-1] == ("stall", "tick 140: 5 ticks skipped before it")
