"""Adaptive playout (jitter) buffer: play each payload at its sender's tick plus a target delay.

Without it a receiver plays a payload on the tick it happens to arrive: one that is a tick late
(a sender's loop stalled, the transport jittered) misses its slot and the receiver conceals a gap,
and one that overtakes another is dropped as stale.  As RTP jitter buffers and WebRTC's NetEQ do,
the buffer instead releases a payload to the decoder at tick ``pkt.tick + d`` of the session clock
(both sides count ticks from the common tick 0 the handshake agreed), and sorts what arrives out of
order within ``d``.

The target ``d`` (ticks) is the low (``LOW_QUANTILE``) quantile of the transit of the payloads of
the last ``AUTO_WINDOW`` ticks (``a_min``: the lowest but for the few that a receiver whose loop ran
late took a tick early, which say nothing about the link), so a lasting route change is followed,
plus an *extra* allowance:

* ``off``: no buffer; a payload goes to the decoder when it arrives (the behaviour before).
* ``MS``: a fixed extra of ``MS`` milliseconds, rounded up to ticks.
* ``auto``: the extra follows the observed lateness ``a - a_min``: the smallest allowance that
  all but ``LATE_SHARE`` (1%) of the payloads of the last ``AUTO_WINDOW`` ticks met, and at least all
  but one of them, where the burst a stalled sender lets go at once (each payload a tick less late
  than the one before) counts as one payload: jitter that delays more than one payload in a hundred
  is covered; a host stall is not (following it would add its delay to every payload for seconds),
  never below ``auto_floor`` ticks.  So: ``d`` ticks of lateness in more than 1% of the
  payloads add ``d`` ticks of delay to all of them; rarer lateness adds nothing, and those payloads
  are played late (counted).  It rises at once and falls when the events leave the window.

On a constant-delay channel ``a`` never varies, so ``auto`` with no floor adds nothing and
``teleop sim`` gives the same bits as without a buffer.  A payload that arrives after its release
tick is *late*: it is released at once (the decoder's newest-wins queue decides what is left of
it), or, if a newer one was already released, dropped as stale by the node, and both are counted.

Delay is passive (eq. 5 holds for any delay): the buffer moves *when* energy is played, never how
much; the energy guard sees each report when its payload is released.  Its cost is transparency
through the wave loop, which the report shows next to the playout delay it used.

Sans-I/O: ``add(pkt, k)`` and ``due(k)`` take the receiver's tick; nothing reads a clock.
"""

from __future__ import annotations

import heapq
import math
from array import array
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from teleop.session import wire

MAX_EXTRA_MS = 500.0  # the largest allowance a user may ask for (and auto may reach)
MAX_HELD = 4096  # packets the buffer holds at most; beyond it the oldest is released at once
AUTO_WINDOW = 2000  # ticks: the auto target looks at the transits of the payloads of the last 2 s
LOW_QUANTILE = 0.05  # of the transits lie below a_min: early payloads, held a little longer
LATE_SHARE = 0.01  # auto: the share of the window's payloads its allowance may leave late
FUTURE_LIMIT = 10_000  # ticks: a payload stamped further ahead than this is released at once
HIST_TICKS = 4096  # bins of the delay histograms (transits beyond are counted in the last)
TRANSIT_LO = -64  # ticks: the lowest transit told apart (below: a clock offset's error, clipped)
CHECK_EVERY = 100  # ticks between looks at the quantiles when nothing forces one
STEP_TICKS = 50  # a payload this much earlier than the lowest transit: the link stepped, start over


def parse_playout(text: str) -> str:
    """Canonical ``off``, ``auto`` or a number of ms (``"2"``); ValueError says what is allowed."""
    t = text.strip().lower()
    if t in ("off", "auto"):
        return t
    what = f"playout must be auto, off or a number of ms 0..{MAX_EXTRA_MS:g}, got {text!r}"
    try:
        ms = float(t.removesuffix("ms"))
    except ValueError:
        raise ValueError(what) from None
    if not 0.0 <= ms <= MAX_EXTRA_MS or not math.isfinite(ms):
        raise ValueError(what)
    return f"{ms + 0.0:g}"  # "-0" is "0": a zero has no sign (PROTOCOL.md 4.2)


@dataclass
class PlayoutStats:
    released: int = 0
    late: int = 0  # arrived after their release tick (released at once, or stale)
    reordered_fixed: int = 0  # arrived after a later payload and still released in order
    overflow: int = 0  # released early because the buffer was full
    future: int = 0  # stamped implausibly far ahead: released at once


class PlayoutBuffer:
    """Holds payloads until ``pkt.tick + target``; see the module docstring."""

    def __init__(self, mode: str, dt: float, auto_floor: int = 0, hold: bool = True) -> None:
        self.mode = parse_playout(mode)
        # hold=False: a replay of a real run's plays (teleop.offline.sim.deliveries): each payload is
        # released when taken, as the run's buffer released it; the target is still kept, from the
        # transits of those plays, for the teleoperator's send phase that follows it.
        self.hold = hold
        self.dt = dt
        self.fixed = 0 if self.mode in ("off", "auto") else math.ceil(float(self.mode) * 1e-3 / dt - 1e-9)
        self.auto_floor = auto_floor
        self.max_extra = math.ceil(MAX_EXTRA_MS * 1e-3 / dt)
        self.extra = self.fixed if self.mode != "auto" else auto_floor
        self._on, self._auto = self.mode != "off", self.mode == "auto"  # the per-payload tests
        # (send tick, seq, n, packet): all held payloads share the current target, so they are
        # released in send order, and a change of target moves them all alike.
        self._heap: list[tuple[int, int, int, wire.Packet]] = []
        self._n = 0
        # One histogram of the transit ``a = k_arrival - pkt.tick`` of the payloads of the last
        # AUTO_WINDOW ticks gives both ends of the target: a_min, its low quantile, and the extra.
        # An array.array of int64, read by numpy without a copy (np.frombuffer): a bin moves by one
        # at every payload, which the array does as fast as a list and about twice as fast as a numpy
        # element cold (no ufunc machinery); its quantile, read every CHECK_EVERY ticks and on every
        # late payload, is numpy's cumsum, ~5 us whatever the transits, where a walk of a list took
        # ~150 us with them at 4 s (measured; issue 22).
        self._hist = array("q", bytes(8 * (HIST_TICKS - TRANSIT_LO + 1)))
        # The window's payloads: the tick each was taken and its histogram bin, in two deques of
        # ints rather than one of tuples: a tuple a payload, alive for AUTO_WINDOW ticks, is what
        # set off most of the cyclic GC's collections of a running process (ints are not tracked).
        self._window_k: deque[int] = deque()
        self._window_b: deque[int] = deque()
        self._a_min: int | None = None
        self._next_check = 0
        self._stale_before = 0  # payloads sent before this tick predate a step: not observed
        self._late_events: deque[tuple[int, int]] = deque()  # (tick, transit) of late payloads
        # How many of them had each transit: the allowance walks the few distinct transits, never
        # every event (a sort of the events on every late payload took ~1 ms once a link's
        # transit sat a tick above a_min for most payloads, which made more of them late).
        self._late_count: dict[int, int] = {}
        self._prev_late = 0
        self._max_seen_tick = -1
        self.stats = PlayoutStats()
        # Histograms (flat memory, whatever the session's length): ticks from each payload's send
        # tick to its release, and the target d at each release; the last bin takes the rest.
        # Lists, not numpy arrays: a bin moves by one at every release, which a list does several
        # times faster than a numpy element (the summary converts them once).
        self.delay_hist = [0] * (HIST_TICKS + 1)
        self.target_hist = [0] * (HIST_TICKS + 1)
        self.extra_hist = [0] * (self.max_extra + 1)

    @property
    def enabled(self) -> bool:
        return self._on

    @property
    def held(self) -> int:
        return len(self._heap)

    @property
    def newest_tick(self) -> int:
        """The highest send tick taken (-1 before any): what the newest payload is due for."""
        return self._max_seen_tick

    def a_min(self) -> int | None:
        return self._a_min

    def target(self) -> int | None:
        """Release tick offset ``d`` from a payload's send tick (None before the first payload)."""
        a = self._a_min
        return None if a is None else a + self.extra

    def _observe(self, a: int, k: int) -> None:
        # Every payload's path (issue 22): the clamps as comparisons, not min(max()); the names
        # read once; mode tested by the flag made at construction.
        hist = self._hist
        b = a - TRANSIT_LO
        if b < 0:
            b = 0
        elif b > HIST_TICKS - TRANSIT_LO:
            b = HIST_TICKS - TRANSIT_LO
        hist[b] += 1
        wk, wb = self._window_k, self._window_b
        wk.append(k)
        wb.append(b)
        old = k - AUTO_WINDOW
        while wk[0] <= old:
            wk.popleft()
            hist[wb.popleft()] -= 1
        a_min = self._a_min
        if a_min is None:
            a_min = self._a_min = a
        if self._auto:
            self._note_late(k, a, a - a_min)
        # The quantiles are looked at only when they may have moved: a payload below the lowest
        # transit or later than the allowance, or every CHECK_EVERY ticks.
        if not (a < a_min or a - a_min > self.extra or k >= self._next_check):
            return
        self._next_check = k + CHECK_EVERY
        self._a_min = self._low_quantile(a)
        if not self._auto:
            return
        # The window is 2 s of events: the allowance falls when they leave it, not before.
        self.extra = self._allowance()

    def _note_late(self, k: int, a: int, late: int) -> None:
        """Lateness events (auto mode): a late payload, or a burst of them that a stalled sender let
        go at once (each a tick less late than the one before: they left together), counts once,
        at its largest lateness; events older than the window are forgotten.  Kept as transits: a
        lateness is counted from the lowest transit when the allowance is worked out (a link whose
        transit stepped up a tick is late by nothing once ``a_min`` has followed it)."""
        prev, self._prev_late = self._prev_late, late
        if late <= 0 or late == prev - 1:
            return
        ev, cnt = self._late_events, self._late_count
        ev.append((k, a))
        cnt[a] = cnt.get(a, 0) + 1
        while ev[0][0] <= k - AUTO_WINDOW:
            self._forget_late(ev.popleft()[1])

    def _forget_late(self, a: int) -> None:
        cnt = self._late_count
        n = cnt[a] - 1
        if n:
            cnt[a] = n
        else:
            del cnt[a]

    def _allowance(self) -> int:
        """The lateness that all but LATE_SHARE of the window's payloads (and at least all but one)
        met, a stalled sender's burst counting as one payload.

        Jitter delays payloads all the time, so it is covered; a host stall delays a burst of
        payloads once, and following it would add its delay to every payload for seconds (it did:
        one 25 ms stall of a sender held `none`'s playout at 25 ms for a whole run; and a host whose
        loops stall a few times a second held it a tick or two above its floor)."""
        ev = self._late_events
        while ev and ev[0][0] <= self._window_k[-1] - AUTO_WINDOW:
            self._forget_late(ev.popleft()[1])
        allowed = max(1, int(LATE_SHARE * len(self._window_k)))
        a_min = self._a_min
        assert a_min is not None
        # The (allowed + 1)-th largest lateness: counted down from the latest transit.
        cnt = self._late_count
        seen = 0
        for a in sorted((a for a in cnt if a > a_min), reverse=True):
            seen += cnt[a]
            if seen > allowed:
                return max(min(a - a_min, self.max_extra), self.auto_floor)
        return self.auto_floor

    def _low_quantile(self, a: int) -> int:
        """The transit LOW_QUANTILE of the recent payloads undercut: the lowest, but for the few a
        receiver that ran late took a tick early (they are only held a tick longer for it)."""
        # No fixed minimum of outliers here: in a short window it would make a_min the highest.
        allowed = int(LOW_QUANTILE * len(self._window_k))
        if allowed == 0:
            return min(a, self._a_min if self._a_min is not None else a)
        below = np.cumsum(np.frombuffer(self._hist, dtype=np.int64))
        return int(np.searchsorted(below, allowed, side="right")) + TRANSIT_LO

    def add(self, pkt: wire.Packet, k: int) -> list[wire.Packet]:
        """A payload taken during tick ``k``; returns what to hand to the node now."""
        if not self._on:
            return [pkt]
        st = self.stats
        tick = pkt.tick
        if tick > k + FUTURE_LIMIT:
            st.future += 1
            return [pkt]
        if tick < self._stale_before:
            # Sent before the link or a clock stepped (forget_transits): it says nothing about the
            # link now; released at once (the node drops it if a newer one went first).
            st.late += 1
            return [pkt]
        a_min = self._a_min
        if a_min is not None and k - tick < a_min - STEP_TICKS:
            # Far earlier than any payload of the window: the link or the sender's clock stepped
            # (a peer whose tick 0 moved, teleop.session.link.phase), not jitter: its old transits are stale.
            self.forget_transits()
        # Lateness is judged against the target this payload was due under (target(), inlined).
        a_min = self._a_min
        before = None if a_min is None else a_min + self.extra
        self._observe(k - tick, k)
        if tick < self._max_seen_tick:
            st.reordered_fixed += 1
        else:
            self._max_seen_tick = tick
        if before is None:  # the first payload: _observe has set a_min
            a_min = self._a_min
            assert a_min is not None
            before = a_min + self.extra
        if tick + before < k:
            st.late += 1
        heapq.heappush(self._heap, (tick, pkt.seq, self._n, pkt))
        self._n += 1
        if len(self._heap) > MAX_HELD:
            st.overflow += 1
            return [self._pop(k)]
        if not self.hold:  # a replay: released when taken (nothing else was held)
            return [self._pop(k)]
        return []

    def _pop(self, k: int) -> wire.Packet:
        pkt = heapq.heappop(self._heap)[3]
        self.stats.released += 1
        delay = k - pkt.tick
        self.delay_hist[HIST_TICKS if delay > HIST_TICKS else delay if delay > 0 else 0] += 1
        a_min, extra = self._a_min, self.extra
        d = 0 if a_min is None else a_min + extra  # target(), None as 0
        self.target_hist[HIST_TICKS if d > HIST_TICKS else d if d > 0 else 0] += 1
        self.extra_hist[extra if extra < self.max_extra else self.max_extra] += 1
        return pkt

    def due(self, k: int) -> list[wire.Packet]:
        """Payloads whose release tick has come, in send order."""
        heap = self._heap
        if not heap:  # most ticks (and every tick with the buffer off): nothing held
            return []
        out = []
        a_min = self._a_min
        until = k - (0 if a_min is None else a_min + self.extra)  # released: send tick + target <= k
        while heap and heap[0][0] <= until:
            out.append(self._pop(k))
        return out

    def pending(self, k: int) -> bool:
        """Whether a payload is held for release by tick ``k``."""
        return bool(self._heap) and self._heap[0][0] + (self.target() or 0) <= k

    def forget_transits(self) -> None:
        """This side's tick 0 moved (``teleop.session.link.phase``: a skewed clock put right): the transits
        seen so far were measured on the old ticks; what is held is released on the new ones."""
        self._hist = array("q", bytes(8 * len(self._hist)))
        self._window_k.clear()
        self._window_b.clear()
        self._a_min = None
        self._next_check = 0
        self.extra = self.fixed if not self._auto else self.auto_floor
        self._late_events.clear()
        self._late_count.clear()
        self._prev_late = 0
        self._stale_before = self._max_seen_tick + 1

    def clear(self) -> None:
        """The sender was replaced: forget what it sent (its ticks and transit start anew)."""
        self._heap.clear()
        self._hist = array("q", bytes(8 * len(self._hist)))
        self._window_k.clear()
        self._window_b.clear()
        self._a_min = None
        self._next_check = 0
        self._late_events.clear()
        self._late_count.clear()
        self._prev_late = 0
        self._max_seen_tick = -1
        self._stale_before = 0

    def delay_ms(self) -> dict[str, float | None]:
        """Send tick to release tick of the payloads so far (ms): p50, p99, max (None: none yet)."""
        return _percentiles(self.delay_hist, self.dt * 1e3)

    def summary(self) -> dict[str, Any]:
        ms = self.dt * 1e3

        def pct(hist: list[int]) -> dict[str, float | None]:
            return _percentiles(hist, ms)

        return {
            "mode": self.mode,
            "auto_floor_ticks": self.auto_floor,
            "extra_ms_final": self.extra * ms,
            "delay_ms": pct(self.delay_hist),
            "target_ms": pct(self.target_hist),
            # The allowance above the lowest transit, at each release: what a simulation needs to
            # play like this run (``teleop.offline.report`` gives it the median as its floor).
            "extra_ms": pct(self.extra_hist),
            **self.stats.__dict__,
        }


def _percentiles(hist: list[int], ms: float) -> dict[str, float | None]:
    h = np.asarray(hist, dtype=np.int64)
    n = int(h.sum())
    if n == 0:
        return {"p50": None, "p99": None, "max": None}
    c = np.cumsum(h)
    return {
        "p50": float(np.searchsorted(c, 0.5 * n)) * ms,
        "p99": float(np.searchsorted(c, 0.99 * n)) * ms,
        "max": float(np.flatnonzero(h)[-1]) * ms,
    }
