"""Receiver-side link measurement: what a link did, from what arrived, not from the shim's settings.

A netem spec says what a link was *asked* to do; correlation, rate queueing, limit drops, tick
rounding and the transport's own jitter all change what it *does*.  :class:`LinkObserver` sees only
the receiver's side (sequence number, the sender's timestamp, size and arrival time of each datagram),
so the same code measures the simulated link and a real one, and its figures can be set against the
spec.

``observe`` runs once per datagram in the 1 kHz loop, so it is O(1) and allocation-light: the
sequence numbers seen go into a sparse bitmap (chunks of 65536 bits, made on first use, so a large or
corrupted uint32 costs one 8 KiB chunk, never an array sized by the largest seq: 0.5 MB an hour at
1 kHz), the one-way delays into a :class:`teleop.session.link.quantiles.Quantiles` (exact for the first 65536
packets, then a fixed histogram), so a session without a fixed end does not grow; percentiles are
computed only in :meth:`LinkObserver.summary`.

Sequence numbers are taken to start at 0 and not to wrap (uint32 at 1 kHz wraps after 49 days).
One-way delay is ``now - t_sent`` on the two ends' session clocks: exact in the simulation (one
clock), offset by the clock difference between two hosts.
"""

from __future__ import annotations

from typing import Any

from teleop.session.link.quantiles import Quantiles

__all__ = ["LinkObserver"]

_CHUNK_BITS = 16  # seqs per bitmap chunk: 2**16 (8 KiB, about a minute at 1 kHz)
_CHUNK_MASK = (1 << _CHUNK_BITS) - 1
_CHUNK_BYTES = (1 << _CHUNK_BITS) // 8


class LinkObserver:
    """Measures loss, one-way delay, duplicates, reordering and throughput of one link direction.

    Call :meth:`observe` for every datagram that arrives (duplicates included), then :meth:`summary`.
    """

    __slots__ = (
        "_bits",
        "_delays",
        "_distinct",
        "_duplicates",
        "_first_t",
        "_last_t",
        "_max_seq",
        "_origin",
        "_origin_from_first",
        "_received",
        "_reordered",
        "_total_bytes",
        "spec",
    )

    def __init__(self, spec: str = "", joined_late: bool = False) -> None:
        """``joined_late``: this receiver joined a running session, so sequence numbers start at the
        first one it sees, not at 0 (the ones before were someone else's)."""
        self.spec = spec  # what the link was configured with, echoed in the summary for reports
        self._origin = 0
        self._origin_from_first = joined_late
        self._bits: dict[int, bytearray] = {}
        self._delays = Quantiles(lo=1e-7, hi=1e3)  # s, first arrival of each seq
        self._distinct = 0
        self._duplicates = 0
        self._reordered = 0
        self._received = 0
        self._total_bytes = 0
        self._max_seq = -1
        self._first_t = 0.0
        self._last_t = 0.0

    def observe(self, now: float, seq: int, t_sent: float, size: int) -> None:
        """One datagram arrived at receiver time ``now`` (s), sent at sender time ``t_sent`` (s)."""
        if self._received == 0:
            self._first_t = now
            if self._origin_from_first:
                self._origin = seq
        self._last_t = now
        self._received += 1
        self._total_bytes += size
        chunk = self._bits.get(seq >> _CHUNK_BITS)
        if chunk is None:
            chunk = self._bits[seq >> _CHUNK_BITS] = bytearray(_CHUNK_BYTES)
        i = seq & _CHUNK_MASK
        mask = 1 << (i & 7)
        if chunk[i >> 3] & mask:
            self._duplicates += 1
            return
        chunk[i >> 3] |= mask
        if seq < self._max_seq:
            self._reordered += 1
        else:
            self._max_seq = seq
        self._delays.add(now - t_sent)
        self._distinct += 1

    def _distinct_below(self, n: int) -> int:
        """Distinct seqs seen in ``[0, n)``."""
        total = 0
        for c, chunk in self._bits.items():
            lo = c << _CHUNK_BITS
            if lo >= n:
                continue
            bits = int.from_bytes(chunk, "little")  # bit i <-> seq lo + i
            if n - lo < (1 << _CHUNK_BITS):
                bits &= (1 << (n - lo)) - 1
            total += bits.bit_count()
        return total

    def quick(self) -> dict[str, Any]:
        """O(1) figures for a live view once a second (no bitmap scan, no percentiles): loss is
        estimated from the highest seq seen, so packets lost after it are not yet counted."""
        expected = self._max_seq + 1 - self._origin
        return {
            "received": self._received,
            "loss_so_far": (expected - self._distinct) / expected if expected > 0 else 0.0,
            "delay_ms_mean": 1e3 * self._delays.total / self._distinct if self._distinct else None,
            "duplicates": self._duplicates,
            "reordered": self._reordered,
        }

    def summary(self, sent: int | None = None, dropped_by_limit: int = 0) -> dict[str, Any]:
        """The measured link (a contract; see the keys below).

        ``sent``: the sender's packet count, when known.  Loss is then counted over seqs ``[0, sent)``,
        which also catches packets lost after the last one that arrived (tail loss); without it, over
        ``[0, max seq seen]``.  ``dropped_by_limit`` is the shim's own count, passed through because a
        receiver cannot tell a queue-limit drop from a loss.

        Keys: ``spec``, ``received`` (datagrams that arrived, duplicates included), ``loss`` (fraction
        of expected seqs never received), ``delay_ms`` {``mean``, ``p50``, ``p99``} (None with no
        arrivals), ``duplicates``, ``reordered``, ``throughput_bps`` (bits of every arrival over the
        span first..last arrival; 0 with fewer than 2 arrivals or a zero span), ``dropped_by_limit``.
        """
        distinct = self._distinct
        o = self._origin
        if sent is None:
            expected, got = self._max_seq + 1 - o, distinct - self._distinct_below(o)
        else:
            expected, got = sent - o, self._distinct_below(sent) - self._distinct_below(o)
        loss = (expected - got) / expected if expected > 0 else 0.0
        delay: dict[str, float | None] = {"mean": None, "p50": None, "p99": None}
        if distinct:
            p50, p99 = self._delays.percentiles([50.0, 99.0])
            delay = {"mean": 1e3 * self._delays.total / distinct, "p50": 1e3 * p50, "p99": 1e3 * p99}
        span = self._last_t - self._first_t
        throughput = 8.0 * self._total_bytes / span if self._received >= 2 and span > 0 else 0.0
        return {
            "spec": self.spec,
            "received": self._received,
            "loss": float(loss),
            "delay_ms": delay,
            "duplicates": self._duplicates,
            "reordered": self._reordered,
            "throughput_bps": float(throughput),
            "dropped_by_limit": int(dropped_by_limit),
        }
