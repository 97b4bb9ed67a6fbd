"""Where the peer's packets land on this side's tick grid, and what the schedule should do about it.

Each side measures, in session, the *apparent transit* of its peer's data packets: the arrival on
its own session clock minus the packet's ``t_us`` (``tick * dt``), in ticks.  It is the one-way
delay plus the error of the handshake's clock offset (where tick 0 landed on this clock), and
since both sides measure against the same nominal tick times, the two errors have opposite signs.
So, with no wire field beyond ``t_us`` (PROTOCOL.md 5.1):

* **Phase** (teleoperator; issue 37): it ticks when the operator's packet is due, i.e. its phase
  ``phi`` (periods after the nominal tick) is the high quantile of the forward transit plus a
  processing margin, modulo a period, held within ``[PHASE_MIN, PHASE_MAX]``.  Then each forward
  payload is played at the first tick after it arrives, and the backward one leaves as early as
  it can, which is what brings the round trip to ``ceil(2 d + processing)``.  The whole-tick part
  of the delay stays with the playout buffer: tick ``k`` keeps meaning the same instant at both
  ends (eq. 7 compares them tick by tick).
* **Skew** (both sides; issue 35): a transit below ``-SKEW_TICKS`` cannot be a delay (a delay only
  lengthens a transit, and the packet is authentic): this side's tick 0 landed later than its
  peer's (an on-path delayer during the handshake made the offset wrong by half of what it added).
  At its next tick the side moves its tick 0 earlier by whole ticks, just enough that no transit
  seen is negative (its loop skips those ticks, counted); the peer's packets that came before its
  own tick 0 often tell it, so on a quiet link it runs aligned, within a tick of its peer, from its
  first tick or so.  What a side cannot see (a skew hidden under a long link's delay) is reported:
  the shift each side made and the transits it measured.

Sans-I/O and deterministic: ``observe`` takes session times, ``take_skew`` is asked before a tick
and ``advance`` after it; the real-time endpoint and ``teleop sim`` call the same methods, so they
keep the same schedule (a skew cannot arise in ``teleop sim``: both ends share its clock).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from teleop.session.link.quantiles import linear_quantile

#: The teleoperator's phase stays within these fractions of a period (it starts at the handshake's
#: ``phase``, 0.5 by default, or earlier): a tick never coincides with the operator's, and a quarter
#: of a period is what a peer's checker can tell from a phase of 0 over loopback (``teleop
#: conformance`` measured 0.1 against 0: 55 us apart at worst, within the host's noise).
PHASE_MIN = 0.25
PHASE_MAX = 0.9
#: Between a packet's arrival and the tick that plays it: the loop's early drain runs up to its spin
#: (10-100 us) before the deadline; this much is kept (s).
PHASE_MARGIN_S = 150e-6
HIGH_QUANTILE = 0.99  # of the transits the phase covers
WINDOW_TICKS = 2000  # the transits of the packets of the last 2 s ...
CAPACITY = 2048  # ... at most this many of them
CHECK_EVERY = 100  # ticks between looks at the quantiles
MIN_SAMPLES = 8  # packets before the first look
#: Periods the phase moves at most per tick: a move is one shorter or longer period, not a slew (a
#: slew earlier would leave each tick's backward packet a little later for its link than the last).
MAX_STEP = 0.5
DEADBAND = 0.02  # periods: a target this close to the phase moves nothing
#: Periods a target must be *earlier* than the phase by before the phase moves earlier (hysteresis).
#: A move earlier leaves each backward packet an outgoing shim holds on the old ticks a whole tick
#: late (released at the first tick after its due time, now a tick on), and the high quantile of a
#: 2 s window moves by tens of microseconds from one look to the next as a sender's late ticks come
#: and go: with the plain deadband, a 10 ms shim link moved the phase 74 times in 15 s, every other
#: look up and down, and 369 of its 462 late backward payloads were such strandings (measured,
#: issue 37).  A phase up to this much later than needed costs the backward payload as much of its
#: tick, never a tick.
EARLIER_DEADBAND = 0.1
SKEW_TICKS = 0.5  # a transit below minus this many ticks is a misplaced tick 0, not a delay
WRAP_MARGIN = 0.2  # periods the transit's p99 must pass a whole tick by before the phase wraps


class ClockTracker:
    """The transits of one side's incoming data packets, and the schedule they call for."""

    def __init__(self, dt: float, phase: float = 0.0, moves_phase: bool = False) -> None:
        self.dt = dt
        self.moves_phase = moves_phase
        self.margin = PHASE_MARGIN_S / dt
        if moves_phase:
            # Start early (just the margin), at most the handshake's ``phase``, and move later as the
            # transits say: a move later never holds back a backward packet an outgoing shim
            # released on the old ticks, where a move earlier left each packet in flight a tick late.
            # Never below PHASE_MIN, whatever the operator proposed (5.1: the robot's own rule).
            phase = max(PHASE_MIN, min(phase, self.margin, PHASE_MAX))
        self.phase = phase  # periods after the nominal tick this side runs (the operator: 0)
        self.target = phase
        self._x = np.zeros(CAPACITY)  # transits, ticks (a ring)
        self._k = np.zeros(CAPACITY, dtype=np.int64)  # the tick each was taken in
        self._n = 0
        self._next_check = 0
        self.shifted_ticks = 0  # tick 0 moved earlier by this many ticks in all (skew)
        self.shifts = 0
        self.phase_moves = 0  # looks that changed the target
        self.first_transit: float | None = None  # ticks, of the first packet (before any shift)
        self._lowest = math.inf  # the lowest transit since the last look at the skew
        self._whole: int | None = None  # the whole ticks of the transit the phase is counted from

    def observe(self, k: int, transit_s: float) -> None:
        """A data packet of the peer taken during tick ``k``, ``transit_s`` after its ``t_us``."""
        x = transit_s / self.dt
        if self.first_transit is None:
            self.first_transit = x
        i = self._n % CAPACITY
        self._x[i] = x
        self._k[i] = k
        self._n += 1
        if x < self._lowest:
            self._lowest = x

    def _window(self, k: int) -> np.ndarray:
        n = min(self._n, CAPACITY)
        x, ks = self._x[:n], self._k[:n]
        return x[ks > k - WINDOW_TICKS]

    def take_skew(self) -> int:
        """Before a tick: the whole ticks to move tick 0 earlier by now (0 mostly), if a packet of the
        peer arrived before it was sent.  One authentic packet is proof enough: a delay, the only
        thing an on-path delayer can add, makes a transit longer, never negative."""
        if self._lowest >= -SKEW_TICKS:
            return 0
        shift = math.ceil(-self._lowest)
        self._x += shift  # the same arrivals, on the moved clock
        self._lowest = math.inf
        if self._whole is not None:
            self._whole += shift
        self.shifted_ticks += shift
        self.shifts += 1
        self._next_check = 0
        return shift

    def advance(self, k: int) -> None:
        """After tick ``k``: :attr:`phase` set for the next tick."""
        if k >= self._next_check and self._n >= MIN_SAMPLES:
            self._next_check = k + CHECK_EVERY
            x = self._window(k)
            if x.size >= MIN_SAMPLES:
                hi = linear_quantile(x, HIGH_QUANTILE)
                if self.moves_phase:
                    u = hi + self.margin
                    # The whole ticks of the transit are the playout buffer's; they change only
                    # past a margin (a p99 that dithers across a tick would flip the phase between
                    # its ends, every packet's tick with it).
                    if self._whole is None or not (
                        self._whole - WRAP_MARGIN <= u < self._whole + 1 + WRAP_MARGIN
                    ):
                        self._whole = math.floor(u)
                    target = min(max(u - self._whole, PHASE_MIN), PHASE_MAX)
                    if target - self.target > DEADBAND or self.target - target > EARLIER_DEADBAND:
                        self.target = float(target)
                        self.phase_moves += 1
        if self.phase != self.target:
            step = min(max(self.target - self.phase, -MAX_STEP), MAX_STEP)
            self.phase = self.target if abs(self.target - self.phase) <= MAX_STEP else self.phase + step

    def summary(self) -> dict[str, Any]:
        """The transits (ms) of the last window, the phase and what the tracker moved."""
        n = min(self._n, CAPACITY)
        ms = self.dt * 1e3
        transit: dict[str, float | None]
        if n:
            p50, p99 = np.quantile(self._x[:n], [0.5, 0.99])
            transit = {"p50": float(p50) * ms, "p99": float(p99) * ms, "min": float(self._x[:n].min()) * ms}
        else:
            transit = {"p50": None, "p99": None, "min": None}
        return {
            "transit_ms": transit,
            "phase": self.phase,
            "phase_moves": self.phase_moves,
            "skew_shift_ms": self.shifted_ticks * ms,
            "skew_shifts": self.shifts,
            "first_transit_ms": None if self.first_transit is None else self.first_transit * ms,
        }


def latency(
    playout: dict[str, dict[str, Any] | None], clock: dict[str, dict[str, Any] | None], dt: float
) -> dict[str, Any]:
    """Sent -> played per direction and the round trip (ms, p50/p99/max), with the floor of the
    measured link beside it, from the receivers' playout and clock summaries (``forward``: the
    teleoperator's, ``backward``: the operator's).

    A payload of tick ``k`` is released at the receiver's tick ``k + n`` (its playout's delay), which
    the teleoperator runs ``phase`` of a period after the operator: forward takes ``n + phase``
    ticks, backward ``n - phase``.  The round trip adds the two (its percentiles the sum of theirs:
    no better than the real one's).  The floor is the smallest whole number of ticks not below the
    link's round trip: the two transits' medians less the phase (the handshake offset's error
    cancels in the sum), at least one tick (two loops that each tick once)."""
    ms = dt * 1e3
    fwd_clock = clock.get("forward") or {}
    phase = float(fwd_clock.get("phase") or 0.0)
    out: dict[str, Any] = {"phase": phase}
    shift = {"forward": phase * ms, "backward": -phase * ms}
    for d in ("forward", "backward"):
        delay = (playout.get(d) or {}).get("delay_ms") or {}
        out[d] = {q: None if delay.get(q) is None else delay[q] + shift[d] for q in ("p50", "p99", "max")}
    out["round_trip"] = {
        q: None
        if out["forward"][q] is None or out["backward"][q] is None
        else out["forward"][q] + out["backward"][q]
        for q in ("p50", "p99", "max")
    }
    tf = (fwd_clock.get("transit_ms") or {}).get("p50")
    tb = ((clock.get("backward") or {}).get("transit_ms") or {}).get("p50")
    link = None if tf is None or tb is None else max(0.0, tf + tb - phase * ms)
    out["link_round_trip_ms"] = link
    # plus the teleoperator's processing between a packet's arrival and its tick
    need = None if link is None else link + PHASE_MARGIN_S * 1e3
    out["floor_ms"] = None if need is None else max(1, math.ceil(need / ms - 1e-6)) * ms
    return out
