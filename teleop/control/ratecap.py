"""A hard data-rate cap in front of any encoder: the minimum instantaneous compression, guaranteed.

The paper (Section III) asks of an LDR scheme the *maximum data rate*, i.e. the minimum
instantaneous compression, that it can guarantee; only the frame-based classes guarantee one by
construction.  :class:`RateCap` guarantees one for any codec: a payload is put on the wire only if
its whole datagram (body, envelope and the transport's header, as the wire counters count it)
fits, together with every datagram sent in the last ``window`` ticks, within ``rate * window``.
Otherwise the payload is held back and the encoder is told (:meth:`teleop.control.codecs.Encoder.cancel`):
an event-based codec (the deadbands) keeps its previous reference and tries again at the next tick,
which adapts its effective threshold to the budget; a periodic one loses that payload, which the
receiver conceals within its energy budget.  Holding back a payload only removes energy, so the cap
never costs passivity.  Within the window the sends are paced (a token bucket a quarter of the
window deep), so a burst cannot spend the whole window and leave the link silent for the rest.

The window matches the report's minimum instantaneous compression (100 ms by default), so the
report's figure is guaranteed, not hoped for: its ``rate_cap.held`` says whether it held on the
wire (the impairment shim's duplicates come after the cap and are not bounded by it).
"""

from __future__ import annotations

from collections import deque

WINDOW_S = 0.1  # s: the sliding window of the cap (and of the report's instantaneous compression)
MIN_RATE_BPS = 8_000.0  # bit/s: 100 B per 100 ms, about one small datagram
MAX_RATE_BPS = 1e10
PACING_DEPTH = 0.25  # of the window's bytes


class RateCap:
    """At most ``rate_bps`` bits per ``window_s``-long sliding window, counting whole datagrams."""

    def __init__(self, rate_bps: float, dt: float, window_s: float = WINDOW_S) -> None:
        if not MIN_RATE_BPS <= rate_bps <= MAX_RATE_BPS:
            raise ValueError(f"rate cap must be {MIN_RATE_BPS:g} to {MAX_RATE_BPS:g} bit/s, got {rate_bps!r}")
        self.rate_bps = rate_bps
        self.window = max(1, round(window_s / dt))
        self.limit_bytes = rate_bps * window_s / 8.0
        # Pacing: a token bucket at the same rate but only PACING_DEPTH of the window deep, so a
        # burst cannot spend the whole window at once and leave the link silent for the rest of it.
        self._rate_per_tick = self.limit_bytes / self.window
        self._depth = self.limit_bytes * PACING_DEPTH
        self._tokens = self._depth
        self._t: int | None = None
        self._sent: deque[tuple[int, int]] = deque()  # (tick, datagram bytes) within the window
        self._bytes = 0
        self.held_back = 0  # payloads the cap did not let out
        self.peak_window_bytes = 0

    def allows(self, k: int, size: int) -> bool:
        """Whether a datagram of ``size`` bytes may leave at tick ``k``."""
        while self._sent and self._sent[0][0] <= k - self.window:
            self._bytes -= self._sent.popleft()[1]
        if self._t is not None and k > self._t:
            self._tokens = min(self._depth, self._tokens + self._rate_per_tick * (k - self._t))
        self._t = k if self._t is None else max(k, self._t)
        if self._bytes + size > self.limit_bytes or (size > self._tokens and size <= self._depth):
            self.held_back += 1
            return False
        return True

    def sent(self, k: int, size: int) -> None:
        self._tokens -= size
        self._sent.append((k, size))
        self._bytes += size
        self.peak_window_bytes = max(self.peak_window_bytes, self._bytes)
