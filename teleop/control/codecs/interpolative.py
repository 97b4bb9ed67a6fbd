"""Interpolative LDR (Section IV.B): passive interpolative down-sampling, iDS.

K samples form a frame; the frame mean (dim p = 1, so c = K by eq. 9) is sent when the frame is
complete and played for the K ticks that follow its arrival.  By Cauchy-Schwarz
``K * mean**2 <= sum(x**2)`` per DoF, which is eq. (8); rounding the mean toward zero only lowers
the played energy.  The frame is played only once its last sample exists: the reconstruction lags
the signal by one frame (K - 1 ticks of filling plus the transport), and the runner shows it.
"""

from __future__ import annotations

import numpy as np

from teleop.control.codecs.base import Array, Encoder, PhasedSchedule, PlayoutDecoder, RawFormat, unpack16


class IdsEncoder(Encoder):
    def __init__(self, raw: RawFormat, k: int, dof: int) -> None:
        self.raw = raw
        self.k = k
        self._sum = np.zeros(dof)
        self._n = 0  # samples in the current frame
        # The frame ends on the call the schedule says; the first one after K calls, as before.
        self._schedule = PhasedSchedule(k)
        self._schedule.due(0)  # call 0 is "before" the first sample: the first frame ends on call K

    def encode(self, x: Array) -> bytes | None:
        self._sum += x
        self._n += 1
        if not self._schedule.due(self.phase):
            return None
        # A frame is K samples, except the one in which the send phase moved (its first or last):
        # then it is m samples and the value sent is sum / sqrt(K m) when m < K, so that the K ticks
        # it is played for still carry at most the frame's energy (Cauchy-Schwarz, eq. 8).
        m = self._n
        mean = self._sum / (m if m >= self.k else np.sqrt(self.k * m))
        self._sum[:] = 0.0
        self._n = 0
        return self.raw.packed16(mean)


class IdsDecoder(PlayoutDecoder):
    def __init__(self, raw: RawFormat, k: int, dof: int, max_queue: int, on_loss: str = "zero") -> None:
        super().__init__(dof, max_queue, on_loss)
        self.raw = raw
        self.k = k

    def parse(self, payload: bytes) -> tuple[Array, int]:
        return self.raw.dequantize(unpack16(payload, self.dof)), self.k
