"""Wire-level byte and packet counters, counted at the socket, per direction.

Every figure comes from datagrams that really crossed the socket: ``wire_bytes`` is the datagram
length plus the UDP/IPv4 headers (28 bytes), ``payload_bytes`` the codec payload inside it.  The
baseline is the uncompressed stream, every tick's raw 16-bit sample in a packet of the same format
(what the ``none`` codec sends); its size is computed in closed form (``teleop.session.wire.packet_size``)
for every tick of the session, never encoded or sent.

Per-tick byte counts keep the time structure (the minimum instantaneous compression over a
sliding window, Section III, and bandwidth over time), but they are not held here for the whole
session: the port's recorder keeps them in its current chunk (``teleop.session.port``), and each sealed
chunk is shown to :meth:`DirectionCounters.window` so the minimum is found as the session runs,
with memory that does not grow.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from teleop.control import metrics

UDP_IPV4_HEADER = 28

Array = npt.NDArray[np.float64]


class DirectionCounters:
    """One direction as seen by one end: what it sent (sender) or received (receiver).

    Totals only; ``on_tick(k, wire_bytes, payload_bytes)``, when set, receives each datagram's
    sizes for the per-tick record (the port's chunked recorder)."""

    def __init__(self, header_bytes: int = UDP_IPV4_HEADER, window_ticks: int = 100) -> None:
        if window_ticks < 1:
            raise ValueError(f"window must be >= 1 tick, got {window_ticks}")
        self.header = header_bytes
        self.window_ticks = window_ticks
        self.on_tick: Callable[[int, int, int], None] | None = None
        self.packets = 0
        self.payload_bytes = 0
        self.wire_bytes = 0
        self.baseline_packets = 0
        self.baseline_payload_bytes = 0
        self.baseline_wire_bytes = 0
        self.malformed = 0
        # The sliding window over the chunks seen so far: the last window - 1 ticks of
        # (baseline wire, wire, baseline payload, payload), and the minimum ratios found.
        self._tail = np.zeros((0, 4))
        self._seen_ticks = 0
        self._min_wire = float("inf")
        self._min_payload = float("inf")
        self.peak_window_wire_bytes = 0.0  # the most wire bytes in any window (a rate cap's check)

    def packet(self, k: int, datagram_len: int, payload_len: int | None) -> None:
        """A datagram sent (or received) during tick ``k``; ``payload_len`` None if unparseable."""
        wire = datagram_len + self.header
        self.packets += 1
        self.wire_bytes += wire
        if payload_len is None:
            self.malformed += 1
        else:
            self.payload_bytes += payload_len
        if self.on_tick is not None:
            self.on_tick(k, wire, payload_len or 0)

    def baseline_bulk(
        self, datagram_lens: npt.NDArray[np.int64], payload_len: int
    ) -> npt.NDArray[np.float64]:
        """The uncompressed stream over some ticks (datagram sizes computed, not encoded): counted in
        the totals; returns each tick's wire bytes (for the per-tick record)."""
        wire = datagram_lens.astype(np.float64) + self.header
        self.baseline_packets += int(wire.size)
        self.baseline_wire_bytes += int(wire.sum())
        self.baseline_payload_bytes += payload_len * int(wire.size)
        return wire

    def window(self, baseline_wire: Array, wire: Array, baseline_payload: Array, payload: Array) -> None:
        """The next ticks of this direction, in order: the minimum instantaneous compression over
        every full window seen so far (``teleop.control.metrics.min_instant_compression``, streamed)."""
        w = self.window_ticks
        block = np.concatenate(
            [self._tail, np.column_stack([baseline_wire, wire, baseline_payload, payload])]
        )
        self._seen_ticks += len(wire)
        sums = np.convolve(block[:, 1], np.ones(w), mode="valid") if len(block) >= w else block[:, 1].sum()
        self.peak_window_wire_bytes = max(self.peak_window_wire_bytes, float(np.max(sums)))
        if len(block) >= w:
            for col, attr in ((1, "_min_wire"), (3, "_min_payload")):
                ratio = metrics.min_instant_compression(block[:, col - 1], block[:, col], w)
                setattr(self, attr, min(getattr(self, attr), ratio))
        self._tail = block[max(0, len(block) - (w - 1)) :] if w > 1 else block[:0]

    def _min_instant(self, wire: bool) -> float:
        if self._seen_ticks < self.window_ticks:  # shorter than one window: the average
            if wire:
                return metrics.compression(self.baseline_wire_bytes, self.wire_bytes)
            return metrics.compression(self.baseline_payload_bytes, self.payload_bytes)
        return self._min_wire if wire else self._min_payload

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "packets": self.packets,
            "payload_bytes": self.payload_bytes,
            "wire_bytes": self.wire_bytes,
            "malformed": self.malformed,
        }
        if self.baseline_packets:
            out.update(
                baseline_packets=self.baseline_packets,
                baseline_payload_bytes=self.baseline_payload_bytes,
                baseline_wire_bytes=self.baseline_wire_bytes,
                compression_payload=metrics.compression(self.baseline_payload_bytes, self.payload_bytes),
                compression_wire=metrics.compression(self.baseline_wire_bytes, self.wire_bytes),
                min_instant_compression_payload=self._min_instant(wire=False),
                min_instant_compression_wire=self._min_instant(wire=True),
            )
        return out
