"""Seeded, sans-I/O link models: Linux netem (``tc-netem``) semantics, and a Mahimahi-style trace link.

A link is driven entirely by its caller: ``send(now, data)`` enqueues, ``due(now)`` returns the packets
whose delivery time has come, ``next_due()`` says when to look again.  Nothing here reads a clock or
draws entropy, so the same seed and the same calls give the same output, in a virtual-time simulation
and in a real-time loop alike.  ``send``/``due`` are O(log n) (a heap), for a 1 kHz control loop.

The netem model follows ``net/sched/sch_netem.c`` (Linux 6.x) and iproute2's ``tc/q_netem.c``:

* per packet, in the kernel's order: duplicate draw, loss draw (a duplicate and a loss on the same
  packet cancel: one copy goes on), corruption of the original, tail drop when ``limit`` packets are
  held, the duplicate re-enters the link (it draws loss, corruption, limit, reorder and delay again,
  is never duplicated again, and is enqueued before the original), then reorder-or-delay;
* ``reorder P [gap N]``: after ``N - 1`` delayed packets each packet is sent at once with probability
  P (which restarts the count), otherwise it is delayed; a reorder needs a delay and ``gap`` defaults
  to 1, as in tc;
* delay is ``TIME`` plus jitter: uniform on ``[TIME - JITTER, TIME + JITTER)`` by default, or
  ``TIME + JITTER * t`` with ``t`` drawn from netem's normal / pareto / paretonormal tables;
* without ``rate`` each packet keeps its own delay, so jitter reorders; with ``rate`` a packet leaves at
  ``max(now + delay, last departure) + (len + overhead) * 8 / rate``, so jitter never reorders;
* correlation is netem's ``get_crandom``: ``u = (1 - c) * uniform + c * last``.  netem's own docs call
  it weak, and it is: the correlated variable is no longer uniform (it bunches around 0.5), so
  ``loss 5% 50%`` loses well under 5% and correlated jitter is narrower than asked;
* loss models: ``random`` (Bernoulli with the correlation above), ``gemodel`` (Gilbert-Elliott: the
  packet's fate is drawn in the state it finds, then the state moves; defaults ``r = 1 - p``,
  ``1-h = 100%``, ``1-k = 0%``) and ``state`` (netem's 4-state GI model; defaults ``p31 = 1 - p13``,
  ``p32 = 0``, ``p23 = 100%``, ``p14 = 0``); both start in the good / gap state.

Where this model differs from netem:

1. Randomness is one ``random.Random(seed)`` (Mersenne Twister) per link; the spec's ``seed N`` wins
   over the constructor's seed, and no seed at all means seed 0 (never entropy).  Same seed, same
   run here; it does not reproduce a kernel run, only its statistics.  The kernel draws corruption
   positions from an unseeded source; here they come from the same seeded stream.
2. Probabilities are floats in [0, 1] compared as ``u < p``, not u32 fixed point (differences of 2**-32).
3. Delay correlation: the kernel reduces the correlated u32 modulo ``2 * jitter`` (in ns) or modulo the
   table size, which discards the correlated high bits unless the jitter is tiny.  Here the
   correlated value is scaled instead, so correlated jitter is actually correlated (and narrowed, the
   weakness noted above).
4. The distribution tables are rebuilt at import from iproute2's generators (``netem/normal.c``,
   ``pareto.c``, ``paretonormal.c``: 4096 entries in units of 1/8192) with the exact inverse normal
   CDF instead of the generators' 5e-5 grid search (differences < 1e-4 jitter).  ``distribution
   uniform`` is accepted and names the built-in default (tc has no ``uniform.dist`` and rejects it).
   ``experimental`` and custom tables are not supported.  paretonormal is, as in iproute2, the
   quantile blend ``(normal + 3 * pareto) / 4`` of the two tables, not a 25/75 mixture.
5. Time is float seconds, not integer ns / psched ticks.  A negative delay (jitter larger than the
   delay) is clamped to 0; the kernel schedules it in the past, which also sends it at once.
6. The kernel's "held in the queue" (for ``limit`` and for ``rate``'s last departure) is here "delivery
   time later than the ``now`` of the latest ``send``/``due`` call": the device is assumed to dequeue
   every packet exactly at its time, so packets that are due but not yet collected by ``due()`` count
   for neither.  ``now`` must not go backwards between calls.
7. A reordered packet gets delivery time ``now``: it precedes everything not yet due, like the
   kernel's head-of-queue insert, but follows packets that were already due at that instant.
8. The duplicate's re-entry assumes netem is the root qdisc (the kernel re-enqueues at the root).
   Corruption flips one bit anywhere in the payload (the kernel: in the linear head); an empty
   payload is never flipped, though the draw is still made, as in the kernel.
9. Parsing is stricter than tc: every option at most once (tc silently keeps the last one, except
   ``loss``); no prefix abbreviations (tc takes ``del`` for ``delay``) nor the ``latency`` / ``drop``
   aliases; ``ecn``, ``slot``, ``rate`` as a percentage of the interface are not supported; ``rate``
   must be > 0 (tc reads 0 as no rate); the 4-state and Gilbert-Elliott probabilities leaving a state
   must sum to at most 100% (the kernel would silently misbehave).

Units, as tc, but a TIME needs its unit (tc reads a bare number as microseconds, and ``delay 50``
ran a session at 50 us where 50 ms was meant; a bare 0 is taken); a bare PERCENT is a percentage
(``5`` is 5%); a bare RATE is bytes/s, and ``bps``/``kbps``/... are *bytes* per second (``kbit``
is 1000 bit/s).

The trace link follows Mahimahi's ``mm-link`` (``link_queue.cc``): the trace lists millisecond
timestamps of delivery opportunities, repeats are allowed, and the trace loops with period equal to
its last timestamp.  Each opportunity carries ``PACKET_SIZE`` = 1504 bytes of the FIFO queue, as in
Mahimahi: several small packets share one opportunity, and a packet that does not fit in what is left
of an opportunity takes those bytes and finishes in a later one (it is delivered at the opportunity
that carries its last byte).  Bytes of an opportunity that finds the queue empty are wasted.  As in
Mahimahi, an opportunity at the very instant a packet arrives is already gone (Mahimahi burns
opportunities up to ``now`` before enqueueing), so a packet never takes the leftover bytes of an
opportunity at or before its arrival.
Differences from Mahimahi:

* a packet over 1504 B (Mahimahi refuses it) is carried the same way, its bytes spilling over as many
  opportunities as they need: ``ceil(len / 1504)`` when it starts on a fresh opportunity;
* the trace starts at ``start`` or, by default, at the first ``send`` (Mahimahi: at link creation);
* the queue is unbounded and lossless (Mahimahi's default ``infinite`` queue).
"""

from __future__ import annotations

import bisect
import functools
import heapq
import itertools
import math
import os
import random
import re
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from statistics import NormalDist
from typing import Any, Protocol

from teleop.errors import LocalError
from teleop.files import MAX_TRACE_BYTES, FileRefused, read_regular

__all__ = [
    "GRAMMAR",
    "PACKET_SIZE",
    "FourStateModel",
    "GEModel",
    "Link",
    "NetemError",
    "NetemLink",
    "NetemSpec",
    "NetemStats",
    "TraceLink",
    "load_trace",
    "make_link",
    "parse_netem",
]

#: Tolerance of ``due(now)``: float sums of ticks must not miss a delivery by one ulp.
EPS = 1e-9

GRAMMAR = """\
netem spec (tc-netem grammar; whitespace-separated tokens, options in any order, each at most once):
  delay TIME [JITTER [CORRELATION]]
  distribution {uniform|normal|pareto|paretonormal}      (needs delay and jitter)
  loss [random] PERCENT [CORRELATION]
  loss state P13 [P31 [P32 [P23 [P14]]]]
  loss gemodel P [R [1-H [1-K]]]
  duplicate PERCENT [CORRELATION]
  reorder PERCENT [CORRELATION] [gap DISTANCE]           (needs a delay)
  corrupt PERCENT [CORRELATION]
  rate RATE [PACKETOVERHEAD [CELLSIZE [CELLOVERHEAD]]]
  limit PACKETS                                          (default 1000)
  seed N
TIME: NUMBER with s|sec|secs|ms|msec|msecs|us|usec|usecs|ns|nsec|nsecs (the unit is required)
PERCENT, CORRELATION: NUMBER[%] in 0..100; a bare number is a percentage
RATE: NUMBER with bit|kbit|mbit|gbit|tbit|kibit|mibit|gibit|tibit (bits/s) or
      bps|kbps|mbps|gbps|tbps|kibps|mibps|gibps|tibps (BYTES/s); a bare number is bytes/s
Optional values are taken only when the next token starts with a digit, as in tc.
Trace link (make_link only): trace FILE"""


class NetemError(LocalError):
    """A bad spec or trace.  ``token`` and ``position`` (token index) say where, when known."""

    def __init__(self, message: str, token: str | None = None, position: int | None = None) -> None:
        super().__init__(message)
        self.token = token
        self.position = position


@dataclass(frozen=True, slots=True)
class GEModel:
    """``loss gemodel``: p = good->bad, r = bad->good, loss probabilities 1-h (bad) and 1-k (good)."""

    p: float
    r: float
    one_minus_h: float = 1.0
    one_minus_k: float = 0.0


@dataclass(frozen=True, slots=True)
class FourStateModel:
    """``loss state``: netem's 4-state GI model (1 gap rx, 2 burst rx, 3 burst loss, 4 isolated loss)."""

    p13: float
    p31: float
    p32: float = 0.0
    p23: float = 1.0
    p14: float = 0.0


@dataclass(frozen=True, slots=True)
class NetemSpec:
    """A parsed netem spec: times in s, probabilities in [0, 1], rate in bit/s; ``text`` for reports."""

    text: str = ""
    limit: int = 1000
    delay: float = 0.0
    jitter: float = 0.0
    delay_corr: float = 0.0
    distribution: str | None = None
    loss: float = 0.0
    loss_corr: float = 0.0
    gemodel: GEModel | None = None
    state_model: FourStateModel | None = None
    duplicate: float = 0.0
    duplicate_corr: float = 0.0
    reorder: float = 0.0
    reorder_corr: float = 0.0
    gap: int = 0
    corrupt: float = 0.0
    corrupt_corr: float = 0.0
    rate: float | None = None
    packet_overhead: int = 0
    cell_size: int = 0
    cell_overhead: int = 0
    seed: int | None = None

    def longest_hold(self, max_len: int) -> float:
        """The longest (s) a link of this spec holds a packet of at most ``max_len`` bytes: its
        delay plus the jitter's widest draw (the distribution table's largest value), plus, with a
        ``rate``, the wait behind a full queue of ``limit`` such packets.  What a robot's envelope
        caps in the backward spec an operator proposes (``teleop.session.settings.Envelope``)."""
        tail = 1.0 if self.distribution in (None, "uniform") else max(dist_tables()[self.distribution])
        hold = max(0.0, self.delay + abs(self.jitter) * tail)
        if self.rate is not None:
            n = max_len + self.packet_overhead
            if self.cell_size:
                n = -(-n // self.cell_size) * (self.cell_size + self.cell_overhead)
            hold += self.limit * max(n, 0) * 8.0 / self.rate
        return hold


@dataclass(slots=True)
class NetemStats:
    """Packet counters; ``sent + duplicated == delivered + lost + dropped_by_limit + in_flight`` always.

    ``duplicated`` counts copies made (a duplicate draw that coincides with a loss makes none, as in the
    kernel); ``reordered`` counts packets sent with no delay by the reorder rule; ``corrupted`` counts
    packets with a bit flipped.
    """

    sent: int = 0
    delivered: int = 0
    lost: int = 0
    duplicated: int = 0
    corrupted: int = 0
    reordered: int = 0
    dropped_by_limit: int = 0


class Link(Protocol):
    """What the simulation runner and the transports use."""

    stats: NetemStats

    def send(self, now: float, data: bytes) -> None: ...

    def due(self, now: float) -> list[bytes]: ...

    def next_due(self) -> float | None: ...


# --- netem's delay distribution tables (iproute2 netem/*.c), in units of jitter -------------------

_DIST_SCALE = 8192  # NETEM_DIST_SCALE
_TABLE_N = 4096  # 16384 / 4 entries, as the generators print


def _s16(v: int) -> int:
    return max(-32768, min(32767, v))


def _normal_entries() -> list[int]:
    inv = NormalDist().inv_cdf
    # normal.c keeps, for each i, the last grid x with rint(16384 * Phi(x)) == i: Phi^-1((i + .5) / 16384).
    return [round(inv((4 * k + 0.5) / 16384) * _DIST_SCALE) for k in range(_TABLE_N)]


def _pareto_entries() -> list[int]:
    out = []
    for k in range(_TABLE_N):
        u = (65536 - 16 * k) / 65536
        d = (u ** (-1.0 / 3.0) - 1.5) * (4.0 / 3.0) * _DIST_SCALE
        out.append(round(min(d, 32767.0)))
    return out


@functools.cache
def dist_tables() -> dict[str, tuple[float, ...]]:
    """Delay tables: delay = TIME + JITTER * table[index], index uniform (or correlated) over the
    table.  Built on first use: at import they took 0.017 s of every command's start."""
    normal = _normal_entries()
    pareto = _pareto_entries()
    blend = []
    for n, p in zip(normal, pareto, strict=True):
        s = n + 3 * p
        blend.append(_s16(-((-s) // 4) if s < 0 else s // 4))  # C integer division truncates
    return {
        "normal": tuple(_s16(v) / _DIST_SCALE for v in normal),
        "pareto": tuple(_s16(v) / _DIST_SCALE for v in pareto),
        "paretonormal": tuple(v / _DIST_SCALE for v in blend),
    }


DISTRIBUTIONS = ("uniform", "normal", "pareto", "paretonormal")


# --- parsing -------------------------------------------------------------------------------------

_NUM = r"(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
_NUM_UNIT = re.compile(rf"({_NUM})([A-Za-z%]*)")
_INT = re.compile(r"\d+")
_SINT = re.compile(r"-?\d+")

_TIME_UNITS = {
    "": 1e-6,
    **dict.fromkeys(("s", "sec", "secs"), 1.0),
    **dict.fromkeys(("ms", "msec", "msecs"), 1e-3),
    **dict.fromkeys(("us", "usec", "usecs"), 1e-6),
    **dict.fromkeys(("ns", "nsec", "nsecs"), 1e-9),
}
_K, _KI = 1e3, 1024.0
_RATE_UNITS = {  # bit/s per unit; tc's table, matched case-insensitively
    "": 8.0,
    "bit": 1.0, "kibit": _KI, "kbit": _K, "mibit": _KI**2, "mbit": _K**2,
    "gibit": _KI**3, "gbit": _K**3, "tibit": _KI**4, "tbit": _K**4,
    "bps": 8.0, "kibps": 8 * _KI, "kbps": 8 * _K, "mibps": 8 * _KI**2, "mbps": 8 * _K**2,
    "gibps": 8 * _KI**3, "gbps": 8 * _K**3, "tibps": 8 * _KI**4, "tbps": 8 * _K**4,
}  # fmt: skip


def _is_number(tok: str) -> bool:
    return tok[:1] in "0123456789" and tok != ""


class _Parser:
    """Walks the token list; every error names the token it stopped at."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.toks = text.split()
        self.i = 0
        self.seen: dict[str, int] = {}

    def error(self, pos: int, reason: str) -> NetemError:
        tok = self.toks[pos] if pos < len(self.toks) else ""
        return NetemError(f"netem: bad token {tok!r} at position {pos}: {reason}\n{GRAMMAR}", tok, pos)

    def take(self, what: str) -> str:
        """The value after the token at ``self.i``; a missing one is blamed on that token."""
        if self.i + 1 >= len(self.toks):
            raise self.error(self.i, f"expected {what} after {self.toks[self.i]!r}, got end of spec")
        self.i += 1
        return self.toks[self.i]

    def next_is_number(self, signed: bool = False) -> bool:
        if self.i + 1 >= len(self.toks):
            return False
        nxt = self.toks[self.i + 1]
        return _is_number(nxt) or (signed and nxt[:1] == "-" and _is_number(nxt[1:]))

    def time(self, what: str) -> float:
        tok = self.take(what)
        m = _NUM_UNIT.fullmatch(tok)
        unit = m.group(2).lower() if m else None
        if m is None or unit not in _TIME_UNITS:
            raise self.error(self.i, f"bad {what}: expected a number with its unit, s|ms|us|ns")
        value = float(m.group(1))
        if unit == "" and value != 0.0:  # tc reads a bare number as us: "delay 50" meant 50 ms?
            raise self.error(
                self.i, f"bad {what}: a time needs its unit (s, ms, us or ns), e.g. {m.group(1)}ms"
            )
        return value * _TIME_UNITS[unit]

    def percent(self, what: str) -> float:
        tok = self.take(what)
        m = _NUM_UNIT.fullmatch(tok)
        if m is None or m.group(2) not in ("", "%"):
            raise self.error(self.i, f"bad {what}: expected a percentage like 5% or 0.5%")
        v = float(m.group(1))
        if not 0.0 <= v <= 100.0:
            raise self.error(self.i, f"bad {what}: a percentage must be within 0..100%")
        return v / 100.0

    def opt_percent(self, what: str, default: float) -> float:
        return self.percent(what) if self.next_is_number() else default

    def integer(self, what: str, signed: bool = False) -> int:
        tok = self.take(what)
        if (_SINT if signed else _INT).fullmatch(tok) is None:
            raise self.error(self.i, f"bad {what}: expected {'an' if signed else 'a non-negative'} integer")
        return int(tok)

    def rate(self) -> float:
        tok = self.take("RATE")
        m = _NUM_UNIT.fullmatch(tok)
        unit = m.group(2).lower() if m else None
        if m is None or unit not in _RATE_UNITS:
            raise self.error(self.i, "bad RATE: expected a number with bit|kbit|mbit|... or bps|kbps|...")
        v = float(m.group(1)) * _RATE_UNITS[unit]
        if not v > 0:
            raise self.error(self.i, "bad RATE: must be > 0")
        return v

    def parse(self) -> NetemSpec:
        f: dict[str, Any] = {"text": self.text}
        handlers: dict[str, Callable[[dict[str, Any]], None]] = {
            "delay": self._delay,
            "distribution": self._distribution,
            "loss": self._loss,
            "duplicate": self._duplicate,
            "reorder": self._reorder,
            "gap": lambda f: f.update(gap=self.integer("DISTANCE")),
            "corrupt": self._corrupt,
            "rate": self._rate,
            "limit": lambda f: f.update(limit=self.integer("PACKETS")),
            "seed": lambda f: f.update(seed=self.integer("N")),
        }
        while self.i < len(self.toks):
            tok = self.toks[self.i]
            handler = handlers.get(tok)
            if handler is None:
                raise self.error(self.i, "unknown option")
            if tok in self.seen:
                raise self.error(self.i, f"duplicate option (first at position {self.seen[tok]})")
            self.seen[tok] = self.i
            handler(f)
            self.i += 1
        return self._check(NetemSpec(**f))

    def _delay(self, f: dict[str, Any]) -> None:
        f["delay"] = self.time("TIME")
        if self.next_is_number():
            f["jitter"] = self.time("JITTER")
            f["delay_corr"] = self.opt_percent("CORRELATION", 0.0)

    def _distribution(self, f: dict[str, Any]) -> None:
        name = self.take("a distribution name")
        if name not in DISTRIBUTIONS:
            raise self.error(self.i, f"unknown distribution, expected one of {'|'.join(DISTRIBUTIONS)}")
        f["distribution"] = name

    def _loss(self, f: dict[str, Any]) -> None:
        kind = self.take("PERCENT or random|state|gemodel")
        if _is_number(kind):
            self.i -= 1
            kind = "random"
        if kind == "random":
            f["loss"] = self.percent("loss PERCENT")
            f["loss_corr"] = self.opt_percent("CORRELATION", 0.0)
        elif kind == "state":
            p13 = self.percent("P13")
            pos13 = self.i
            vals = {"p13": p13, "p31": 1.0 - p13, "p32": 0.0, "p23": 1.0, "p14": 0.0}
            pos = {"p31": pos13, "p32": pos13, "p14": pos13}
            for name in ("p31", "p32", "p23", "p14"):
                if not self.next_is_number():
                    break
                vals[name] = self.percent(name.upper())
                pos[name] = self.i
            if vals["p13"] + vals["p14"] > 1.0 + 1e-12:
                raise self.error(pos["p14"], "P13 + P14 must be at most 100% (both leave state 1)")
            if vals["p31"] + vals["p32"] > 1.0 + 1e-12:
                pos31 = max(pos["p31"], pos["p32"])
                raise self.error(pos31, "P31 + P32 must be at most 100% (both leave state 3)")
            f["state_model"] = FourStateModel(**vals)
        elif kind == "gemodel":
            p = self.percent("P")
            r = self.opt_percent("R", 1.0 - p)  # iproute2 >= 5.2; before, r defaulted to 100% (a bug)
            h1 = self.opt_percent("1-H", 1.0)
            k1 = self.opt_percent("1-K", 0.0)
            f["gemodel"] = GEModel(p, r, h1, k1)
        else:
            raise self.error(self.i, "unknown loss model, expected PERCENT or random|state|gemodel")

    def _duplicate(self, f: dict[str, Any]) -> None:
        f["duplicate"] = self.percent("duplicate PERCENT")
        f["duplicate_corr"] = self.opt_percent("CORRELATION", 0.0)

    def _reorder(self, f: dict[str, Any]) -> None:
        f["reorder"] = self.percent("reorder PERCENT")
        f["reorder_corr"] = self.opt_percent("CORRELATION", 0.0)

    def _corrupt(self, f: dict[str, Any]) -> None:
        f["corrupt"] = self.percent("corrupt PERCENT")
        f["corrupt_corr"] = self.opt_percent("CORRELATION", 0.0)

    def _rate(self, f: dict[str, Any]) -> None:
        f["rate"] = self.rate()
        if self.next_is_number(signed=True):
            f["packet_overhead"] = self.integer("PACKETOVERHEAD", signed=True)
            if self.next_is_number():
                f["cell_size"] = self.integer("CELLSIZE")
                if self.next_is_number(signed=True):
                    f["cell_overhead"] = self.integer("CELLOVERHEAD", signed=True)

    def _check(self, spec: NetemSpec) -> NetemSpec:
        """tc's cross-option checks, after all options are read."""
        if "reorder" in self.seen and spec.reorder > 0:
            if spec.delay == 0:
                raise self.error(self.seen["reorder"], "reordering is not possible without some delay")
            if spec.gap == 0:
                spec = replace(spec, gap=1)
        elif "gap" in self.seen and spec.gap > 0:
            raise self.error(self.seen["gap"], "gap given without a reorder probability")
        if "distribution" in self.seen and (spec.delay == 0 or spec.jitter == 0):
            raise self.error(self.seen["distribution"], "distribution given without delay and jitter")
        return spec


def parse_rate(text: str) -> float:
    """One RATE in tc's units (``64kbit``; ``kbps`` is kilobytes/s), in bit/s; NetemError if bad."""
    m = _NUM_UNIT.fullmatch(text.strip())
    unit = m.group(2).lower() if m else None
    if m is None or unit not in _RATE_UNITS:
        raise NetemError("expected a number with bit|kbit|mbit|... (bits/s) or bps|kbps|... (bytes/s)", text)
    v = float(m.group(1)) * _RATE_UNITS[unit]
    if not (v > 0 and math.isfinite(v)):
        raise NetemError("a rate must be finite and > 0", text)
    return v


def parse_netem(text: str) -> NetemSpec:
    """Parse a netem option string (what follows ``tc qdisc ... netem``); "" is a clean link."""
    return _Parser(text).parse()


# --- the netem link ------------------------------------------------------------------------------


class _CRandom:
    """netem's ``get_crandom``: ``u = (1 - c) * uniform + c * last``; plain uniform when ``c == 0``."""

    __slots__ = ("_rand", "last", "rho")

    def __init__(self, rho: float, rand: Callable[[], float]) -> None:
        self._rand = rand
        self.rho = rho
        self.last = rand() if rho > 0 else 0.0

    def __call__(self) -> float:
        if self.rho == 0.0:
            return self._rand()
        self.last = (1.0 - self.rho) * self._rand() + self.rho * self.last
        return self.last


class NetemLink:
    """One direction of a netem-impaired link (see the module docstring for semantics and deviations)."""

    def __init__(self, spec: NetemSpec, seed: int | None = None) -> None:
        self.spec = spec
        self.stats = NetemStats()
        self._rng = random.Random(spec.seed if spec.seed is not None else (seed or 0))
        rand = self._rng.random
        self._rand = rand
        self._dup_cor = _CRandom(spec.duplicate_corr, rand)
        self._loss_cor = _CRandom(spec.loss_corr, rand)
        self._corrupt_cor = _CRandom(spec.corrupt_corr, rand)
        self._reorder_cor = _CRandom(spec.reorder_corr, rand)
        self._delay_cor = _CRandom(spec.delay_corr, rand)
        self._table = dist_tables().get(spec.distribution or "uniform")
        self._loss_event: Callable[[], bool]
        if spec.state_model is not None:
            self._loss_event = self._loss_4state
        elif spec.gemodel is not None:
            self._loss_event = self._loss_gilb_ell
        elif spec.loss > 0:
            self._loss_event = self._loss_random
        else:
            self._loss_event = _never
        self._ge_bad = False
        self._state = 1  # TX_IN_GAP_PERIOD
        self._counter = 0  # packets delayed since the last reorder
        self._last_tx = -math.inf  # latest delivery time scheduled so far
        self._heap: list[tuple[float, int, bytes]] = []
        self._ready: list[tuple[float, int, bytes]] = []  # due as of the last call, not yet collected
        self._seq = 0

    @property
    def in_flight(self) -> int:
        """Packets sent and neither delivered nor dropped yet."""
        return len(self._heap) + len(self._ready)

    def send(self, now: float, data: bytes) -> None:
        self.stats.sent += 1
        self._advance(now)
        self._enqueue(now, data, True)

    def due(self, now: float) -> list[bytes]:
        heap = self._heap
        if not self._ready and (not heap or heap[0][0] > now + EPS):
            return []
        self._advance(now)
        out = [item[2] for item in self._ready]
        self._ready.clear()
        self.stats.delivered += len(out)
        return out

    def next_due(self) -> float | None:
        if self._ready:
            return self._ready[0][0]
        return self._heap[0][0] if self._heap else None

    def _advance(self, now: float) -> None:
        """Move what is due to ``_ready``, so the heap holds exactly what the kernel's queue would."""
        heap = self._heap
        limit = now + EPS
        while heap and heap[0][0] <= limit:
            self._ready.append(heapq.heappop(heap))

    def _enqueue(self, now: float, data: bytes, may_duplicate: bool) -> None:
        """``netem_enqueue``, step by step."""
        spec = self.spec
        count = 1
        if may_duplicate and spec.duplicate > 0 and self._dup_cor() < spec.duplicate:
            count += 1
        if self._loss_event():
            count -= 1
        if count == 0:
            self.stats.lost += 1
            return
        copy = data if count > 1 else None
        if spec.corrupt > 0 and self._corrupt_cor() < spec.corrupt and data:
            buf = bytearray(data)
            buf[self._rng.randrange(len(buf))] ^= 1 << self._rng.randrange(8)
            data = bytes(buf)
            self.stats.corrupted += 1
        if copy is not None:
            self.stats.duplicated += 1
        if len(self._heap) >= spec.limit:
            self.stats.dropped_by_limit += count
            return
        if copy is not None:
            self._enqueue(now, copy, False)
        if spec.gap == 0 or self._counter < spec.gap - 1 or self._reorder_cor() >= spec.reorder:
            t = now + max(self._delay(), 0.0)
            if spec.rate is not None:
                t = max(t, self._last_tx) + self._packet_time(len(data))
            self._counter += 1
        else:
            t = now
            self._counter = 0
            self.stats.reordered += 1
        if t > self._last_tx:
            self._last_tx = t
        heapq.heappush(self._heap, (t, self._seq, data))
        self._seq += 1

    def _delay(self) -> float:
        """``tabledist``: the delay for one packet, before clamping at 0."""
        spec = self.spec
        if spec.jitter == 0.0:
            return spec.delay
        u = self._delay_cor()
        table = self._table
        if table is None:
            return spec.delay + spec.jitter * (2.0 * u - 1.0)
        return spec.delay + spec.jitter * table[int(u * len(table))]

    def _packet_time(self, length: int) -> float:
        spec = self.spec
        n = length + spec.packet_overhead
        if spec.cell_size:
            n = -(-n // spec.cell_size) * (spec.cell_size + spec.cell_overhead)
        assert spec.rate is not None
        return max(n, 0) * 8.0 / spec.rate

    def _loss_random(self) -> bool:
        return self._loss_cor() < self.spec.loss

    def _loss_gilb_ell(self) -> bool:
        """``loss_gilb_ell``: fate drawn in the current state, after the transition draw."""
        ge = self.spec.gemodel
        assert ge is not None
        rand = self._rand
        if not self._ge_bad:
            if rand() < ge.p:
                self._ge_bad = True
            return rand() < ge.one_minus_k
        if rand() < ge.r:
            self._ge_bad = False
        return rand() < ge.one_minus_h

    def _loss_4state(self) -> bool:
        """``loss_4state``: one draw moves the chain; a packet is lost on entering state 3 or 4."""
        m = self.spec.state_model
        assert m is not None
        u = self._rand()
        s = self._state
        if s == 1:
            if u < m.p14:
                self._state = 4
                return True
            if u < m.p13 + m.p14:
                self._state = 3
                return True
            return False
        if s == 2:
            if u < m.p23:
                self._state = 3
                return True
            return False
        if s == 3:
            if u < m.p32:
                self._state = 2
                return False
            if u < m.p31 + m.p32:
                self._state = 1
                return False
            return True
        self._state = 1
        return False


def _never() -> bool:
    return False


# --- the trace link ------------------------------------------------------------------------------


def load_trace(path_or_text: str | os.PathLike[str]) -> list[float]:
    """A Mahimahi trace as a list of ms timestamps.

    A path-like is read as a file; a ``str`` is trace text if it contains a newline, else a path.
    The file is read through :func:`teleop.files.read_regular` (a regular file of at most
    :data:`teleop.files.MAX_TRACE_BYTES`), the one place the core opens an input.
    One number per line (blank lines skipped), non-negative, non-decreasing, last one > 0.
    """
    if isinstance(path_or_text, str) and "\n" in path_or_text:
        text, name = path_or_text, "<text>"
    else:
        name = os.fspath(path_or_text)
        try:  # a regular file of bounded size only: a FIFO or /dev/zero is refused by its type
            text = read_regular(name, MAX_TRACE_BYTES, "trace").decode()
        except FileRefused as e:
            raise NetemError(str(e)) from None
        except UnicodeDecodeError:
            raise NetemError(f"trace {name}: not text (a trace is ms timestamps, one a line)") from None
    out: list[float] = []
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line:
            continue
        try:
            ms = float(line)
        except ValueError:
            # Quote a short bad line only: a file that is not a trace (say /etc/shadow) must not
            # have its contents printed back.
            shown = repr(line) if len(line) <= 16 else f"a line of {len(line)} characters"
            raise NetemError(f"trace {name}: line {lineno}: {shown} is not a number of ms", line) from None
        if not (math.isfinite(ms) and ms >= 0):
            raise NetemError(f"trace {name}: line {lineno}: {line!r} must be a finite ms >= 0", line)
        if out and ms < out[-1]:
            raise NetemError(f"trace {name}: line {lineno}: timestamps must be non-decreasing", line)
        out.append(ms)
    if not out:
        raise NetemError(f"trace {name}: no timestamps")
    if out[-1] <= 0:
        raise NetemError(f"trace {name}: must last a nonzero time (last timestamp is 0)")
    return out


#: Mahimahi's ``PACKET_SIZE``: bytes one delivery opportunity carries (its max TUN payload).
PACKET_SIZE = 1504


class TraceLink:
    """A Mahimahi-style trace-driven link: FIFO, 1504 bytes per delivery opportunity (see the module doc).

    The queue is FIFO and the opportunities are fixed in advance, so a packet's delivery time is known
    when it is sent: the link keeps only the opportunity that carried the last byte queued so far and
    the bytes left in it.
    """

    def __init__(
        self, trace_ms: Sequence[float], *, start: float | None = None, packet_size: int = PACKET_SIZE
    ) -> None:
        if not trace_ms or trace_ms[-1] <= 0 or any(b < a for a, b in itertools.pairwise(trace_ms)):
            raise NetemError("trace must be non-empty, non-decreasing and last a nonzero time")
        if packet_size < 1:
            raise NetemError(f"packet_size must be >= 1 B, got {packet_size}")
        self.stats = NetemStats()
        self._trace = [float(t) for t in trace_ms]
        self._n = len(self._trace)
        self._period = self._trace[-1]
        self._epoch = start
        self._size = packet_size
        self._k = -1  # opportunity that carries the last byte queued so far (-1: none yet)
        self._left = 0  # bytes of opportunity ``_k`` not yet taken
        self._queue: deque[tuple[float, bytes]] = deque()

    @property
    def in_flight(self) -> int:
        return len(self._queue)

    def _opp_time(self, k: int) -> float:
        c, j = divmod(k, self._n)
        assert self._epoch is not None
        return self._epoch + (c * self._period + self._trace[j]) * 1e-3

    def _first_opp_after(self, now: float) -> int:
        """Index of the first opportunity later than ``now`` (one at ``now`` is already gone)."""
        assert self._epoch is not None
        rel = (now - self._epoch) * 1e3
        c = max(0, int(rel // self._period))
        k = c * self._n + bisect.bisect_right(self._trace, rel - c * self._period)
        limit = now + EPS
        while self._opp_time(k) <= limit:  # float edges only: a step or two at most
            k += 1
        while k > 0 and self._opp_time(k - 1) > limit:
            k -= 1
        return k

    def send(self, now: float, data: bytes) -> None:
        if self._epoch is None:
            self._epoch = now
        self.stats.sent += 1
        if self._k >= 0 and self._opp_time(self._k) > now + EPS:
            k, left = self._k, self._left  # queue still busy at opportunity k: share its leftover
        else:
            k, left = self._first_opp_after(now), self._size  # idle: the leftover went unused
        need = len(data)
        if left == 0:  # Mahimahi's loop stops at 0 bytes left, even for an empty packet
            k, left = k + 1, self._size
        if need > left:
            need -= left
            m = -(-need // self._size)
            k, left = k + m, m * self._size - need
        else:
            left -= need
        self._k, self._left = k, left
        self._queue.append((self._opp_time(k), data))

    def due(self, now: float) -> list[bytes]:
        q = self._queue
        limit = now + EPS
        out = []
        while q and q[0][0] <= limit:
            out.append(q.popleft()[1])
        self.stats.delivered += len(out)
        return out

    def next_due(self) -> float | None:
        return self._queue[0][0] if self._queue else None


def make_link(spec_text: str | None, seed: int) -> Link:
    """A link from a spec: "" / None -> clean zero-delay link, ``trace FILE`` -> TraceLink, else netem."""
    text = (spec_text or "").strip()
    toks = text.split()
    if toks and toks[0] == "trace":
        if len(toks) != 2:
            pos = min(len(toks) - 1, 2)
            raise NetemError(
                f"netem: bad token {toks[pos]!r} at position {pos}: expected exactly 'trace FILE'\n{GRAMMAR}",
                toks[pos],
                pos,
            )
        return TraceLink(load_trace(Path(toks[1])))
    return NetemLink(parse_netem(text), seed)
