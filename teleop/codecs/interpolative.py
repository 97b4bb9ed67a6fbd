"""Interpolative LDR (Section IV.B): passive interpolative down-sampling, iDS.

K samples form a frame; the frame mean (dim p = 1, so c = K by eq. 9) is sent when the frame is
complete and played for the K ticks that follow its arrival.  By Cauchy-Schwarz
``K * mean**2 <= sum(x**2)`` per DoF, which is eq. (8); rounding the mean toward zero only lowers
the played energy.  The frame is played only once its last sample exists: the reconstruction lags
the signal by one frame (K - 1 ticks of filling plus the transport), and the runner shows it.
"""

from __future__ import annotations

import numpy as np

from .base import Array, Encoder, PlayoutDecoder, RawFormat, pack, unpack


class IdsEncoder(Encoder):
    def __init__(self, raw: RawFormat, k: int, dof: int) -> None:
        self.raw = raw
        self.k = k
        self._sum = np.zeros(dof)
        self._n = 0

    def encode(self, x: Array) -> bytes | None:
        self._sum += x
        self._n += 1
        if self._n < self.k:
            return None
        mean = self._sum / self.k
        self._sum[:] = 0.0
        self._n = 0
        return pack(self.raw.quantize(mean), 16)


class IdsDecoder(PlayoutDecoder):
    def __init__(self, raw: RawFormat, k: int, dof: int, max_queue: int, on_loss: str = "zero") -> None:
        super().__init__(dof, max_queue, on_loss)
        self.raw = raw
        self.k = k

    def parse(self, payload: bytes) -> tuple[Array, int]:
        return self.raw.dequantize(unpack(payload, 16, self.dof)), self.k
