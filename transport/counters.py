"""Wire-level byte and packet counters, counted at the socket, per direction.

Every figure comes from datagrams that really crossed the socket: ``wire_bytes`` is the datagram
length plus the UDP/IPv4 headers (28 bytes), ``payload_bytes`` the codec payload inside it.  The
baseline is the uncompressed stream, every tick's raw 16-bit sample in a packet of the same format
(what the ``none`` codec sends); its size is computed in closed form (``teleop.wire.packet_size``)
for every tick of the session, never encoded or sent.

Per-tick arrays keep the time structure, so the report can give the minimum instantaneous
compression over a sliding window (Section III) and bandwidth over time.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from teleop import metrics

UDP_IPV4_HEADER = 28

Array = npt.NDArray[np.float64]


class _PerTick:
    def __init__(self, ticks: int) -> None:
        self.a = np.zeros(max(ticks, 1))

    def add(self, k: int, v: float) -> None:
        self.a[min(max(k, 0), self.a.size - 1)] += v


class DirectionCounters:
    """One direction as seen by one end: what it sent (sender) or received (receiver)."""

    def __init__(self, ticks: int, header_bytes: int = UDP_IPV4_HEADER) -> None:
        self.header = header_bytes
        self.packets = 0
        self.payload_bytes = 0
        self.wire_bytes = 0
        self.baseline_packets = 0
        self.baseline_payload_bytes = 0
        self.baseline_wire_bytes = 0
        self.malformed = 0
        self.wire_per_tick = _PerTick(ticks)
        self.payload_per_tick = _PerTick(ticks)
        self.baseline_wire_per_tick = _PerTick(ticks)
        self.baseline_payload_per_tick = _PerTick(ticks)

    def packet(self, k: int, datagram_len: int, payload_len: int | None) -> None:
        """A datagram sent (or received) during tick ``k``; ``payload_len`` None if unparseable."""
        wire = datagram_len + self.header
        self.packets += 1
        self.wire_bytes += wire
        self.wire_per_tick.add(k, wire)
        if payload_len is None:
            self.malformed += 1
        else:
            self.payload_bytes += payload_len
            self.payload_per_tick.add(k, payload_len)

    def baseline(self, k: int, datagram_len: int, payload_len: int) -> None:
        """What the uncompressed stream would have sent at tick ``k``."""
        wire = datagram_len + self.header
        self.baseline_packets += 1
        self.baseline_wire_bytes += wire
        self.baseline_payload_bytes += payload_len
        self.baseline_wire_per_tick.add(k, wire)
        self.baseline_payload_per_tick.add(k, payload_len)

    def baseline_bulk(
        self, ks: npt.NDArray[np.intp], datagram_lens: npt.NDArray[np.int64], payload_len: int
    ) -> None:
        """The uncompressed stream at ticks ``ks`` at once (datagram sizes computed, not encoded)."""
        wire = datagram_lens.astype(np.float64) + self.header
        ks = np.clip(ks, 0, self.baseline_wire_per_tick.a.size - 1)
        self.baseline_packets += int(ks.size)
        self.baseline_wire_bytes += int(wire.sum())
        self.baseline_payload_bytes += payload_len * int(ks.size)
        np.add.at(self.baseline_wire_per_tick.a, ks, wire)
        np.add.at(self.baseline_payload_per_tick.a, ks, float(payload_len))

    def summary(self, window_ticks: int = 100) -> dict[str, Any]:
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
                min_instant_compression_payload=metrics.min_instant_compression(
                    self.baseline_payload_per_tick.a, self.payload_per_tick.a, window_ticks
                ),
                min_instant_compression_wire=metrics.min_instant_compression(
                    self.baseline_wire_per_tick.a, self.wire_per_tick.a, window_ticks
                ),
            )
        return out

    def arrays(self, prefix: str) -> dict[str, Array]:
        d = {f"{prefix}_wire": self.wire_per_tick.a, f"{prefix}_payload": self.payload_per_tick.a}
        if self.baseline_packets:
            d[f"{prefix}_baseline_wire"] = self.baseline_wire_per_tick.a
        return d
