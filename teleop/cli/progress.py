"""Progress of a command that runs many cases (``teleop sweep``, ``teleop experiment``): the case
count, the time spent and an estimate of the time left, from the mean time a case took so far.

A one-line bar rewritten in place on a terminal; one line per case otherwise (a log file stays
readable).  Hand-written rather than a progress library: one line, no new dependency."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TextIO


def duration_text(s: float) -> str:
    """``42 s``, ``3 min 05 s``, ``1 h 02 min``."""
    s = max(0.0, s)
    if s < 60:
        return f"{s:.0f} s"
    if s < 3600:
        return f"{int(s // 60)} min {int(s % 60):02d} s"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"


@dataclass
class Progress:
    total: int
    stream: TextIO
    prefix: str = ""
    done: int = 0
    clock: Callable[[], float] = time.monotonic
    _t0: float = field(default=0.0, init=False)

    def __post_init__(self) -> None:
        self._t0 = self.clock()

    def text(self, what: str) -> str:
        spent = self.clock() - self._t0
        left = spent / self.done * (self.total - self.done) if self.done else 0.0
        tail = "done" if self.done >= self.total else f"about {duration_text(left)} left"
        return f"{self.done}/{self.total} {what}  ({duration_text(spent)} spent, {tail})"

    def step(self, what: str) -> None:
        self.done += 1
        line = self.text(what)
        if self.stream.isatty():
            bar = "#" * (20 * self.done // self.total)
            self.stream.write(f"\r{self.prefix}[{bar:<20}] {line:<70}")
            if self.done == self.total:
                self.stream.write("\n")
        else:
            self.stream.write(f"{self.prefix}{line}\n")
        self.stream.flush()
