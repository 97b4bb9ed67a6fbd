"""Extrapolative LDR (Section IV.C): passive extrapolative down-sampling, eDS.

Every K ticks the latest sample is sent and held by the receiver for the next K ticks (zero-order
extrapolation, dim p = 1, c = K).  The sender knows exactly what the receiver will play, so it keeps
the budget of eq. (10) per DoF::

    budget = sum_{m <= n} x[m]**2  -  sum of everything already scheduled for playing

and when ``K * x**2`` would exceed it, sends ``sign(x) * sqrt(budget / K)`` instead: "a value
computed such that (10) is satisfied" (Section V.B).  No delay is added.
"""

from __future__ import annotations

import numpy as np

from teleop.control.codecs.base import (
    Array,
    Encoder,
    PhasedSchedule,
    PlayoutDecoder,
    RawFormat,
    pack,
    unpack16,
)


class EdsEncoder(Encoder):
    def __init__(self, raw: RawFormat, k: int, dof: int) -> None:
        self.raw = raw
        self.k = k
        self._energy_in = np.zeros(dof)  # sum of x**2 (energy / dt), per DoF
        self._energy_out = np.zeros(dof)  # sum of played p**2 over all horizons sent
        self._schedule = PhasedSchedule(k)
        self._last_out = np.zeros(dof)  # energy the last horizon added to _energy_out (for cancel)
        self.limited = 0  # horizons whose value the budget cut down

    def encode(self, x: Array) -> bytes | None:
        self._energy_in += x * x
        if not self._schedule.due(self.phase):
            return None
        if self.power:  # a power variable: plain zero-order hold, TDPA guards the energy
            return self.raw.packed16(x)
        budget = np.maximum(self._energy_in - self._energy_out, 0.0)
        want = self.k * x * x
        over = want > budget
        p = x
        if over.any():
            self.limited += 1
            p = np.where(over, np.sign(x) * np.sqrt(budget / self.k), x)
        q = self.raw.quantize(p)
        played = self.raw.dequantize(q)
        self._last_out = self.k * played * played
        self._energy_out += self._last_out
        return pack(q, 16)

    def cancel(self) -> None:
        """The horizon was not sent: nothing of it will be played (the receiver conceals)."""
        self._energy_out -= self._last_out
        self._last_out = np.zeros_like(self._last_out)


class EdsDecoder(PlayoutDecoder):
    def __init__(self, raw: RawFormat, k: int, dof: int, max_queue: int, on_loss: str = "zero") -> None:
        super().__init__(dof, max_queue, on_loss)
        self.raw = raw
        self.k = k

    def parse(self, payload: bytes) -> tuple[Array, int]:
        return self.raw.dequantize(unpack16(payload, self.dof)), self.k
