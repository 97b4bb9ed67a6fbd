"""bench/fleet.py's verdicts: what counts as broken at a step (the figure the docs print)."""

from __future__ import annotations

from typing import Any

import pytest

from bench.fleet import broke


def result(**kw: Any) -> dict[str, Any]:
    base: dict[str, Any] = {"warm": True, "loss": 0.0, "rate_achieved": 1000.0, "rtt_us": {"p50": 400.0}}
    return {**base, **kw}


def test_a_step_that_keeps_up_is_not_broken() -> None:
    assert broke(result(), 1000.0) is None
    assert broke(result(rate_achieved=30.0, rtt_us={"p50": 30_000.0}), 30.0) is None  # under 33 ms


@pytest.mark.parametrize(
    ("kw", "said"),
    [
        ({"warm": False}, "route"),
        ({"loss": 0.02}, "2.0% of echoes lost"),
        ({"rate_achieved": 900.0}, "kept 900 of 1000"),
        ({"rtt_us": {"p50": 1500.0}}, "a queue builds"),
    ],
)
def test_each_way_of_breaking_is_named(kw: dict[str, Any], said: str) -> None:
    got = broke(result(**kw), 1000.0)
    assert got is not None and said in got, got
