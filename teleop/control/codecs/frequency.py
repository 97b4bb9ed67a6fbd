"""Frequency-based LDR (Section IV.A): the M lowest DCT-II coefficients of each frame of N samples.

The paper describes this class and builds none.  Here N samples per DoF form a frame; the sender
transforms it with the orthonormal DCT-II, keeps the ``M`` lowest coefficients, rounds each toward
zero in the raw 16-bit format, and sends them when the frame is complete (c = N/M, eq. 9).  The
receiver applies the inverse transform to the truncated coefficients and plays the N samples of the
frame, one frame later, like ``ids`` (which is ``dct:N:1`` up to the scale of its one coefficient).

Passive by Parseval: the transform is orthonormal, so the played frame's energy is the sum of the
kept coefficients' squares, which is at most the sum of all of them, the frame's energy.  Rounding
toward zero only lowers it.  That is eq. (8), frame by frame; a hypothesis test checks it.

The DCT concentrates a smooth frame in its first coefficients (energy compaction), which is why it
beats the frame mean of ``ids`` at the same rate, at the price of the same frame of delay.
"""

from __future__ import annotations

import numpy as np

from teleop.control.codecs.base import Array, Encoder, PlayoutDecoder, RawFormat, unpack16

MAX_FRAME = 1000  # ticks: a frame is buffered whole; longer ones would also add seconds of delay


def dct_basis(n: int, m: int) -> Array:
    """Rows 0..m-1 of the orthonormal DCT-II matrix of size n (so ``C @ C.T == I_m``)."""
    k = np.arange(m, dtype=np.float64)[:, None]
    i = np.arange(n, dtype=np.float64)[None, :]
    c = np.sqrt(2.0 / n) * np.cos(np.pi * (i + 0.5) * k / n)
    c[0] /= np.sqrt(2.0)
    out: Array = c
    return out


def coefficient_format(raw: RawFormat, n: int) -> RawFormat:
    """Coefficients of a frame within the wave range reach ``sqrt(N)`` times the range (DC term)."""
    return RawFormat(raw.full_scale * np.sqrt(n))


class DctEncoder(Encoder):
    def __init__(self, raw: RawFormat, n: int, m: int, dof: int) -> None:
        self.raw = coefficient_format(raw, n)
        self.basis = dct_basis(n, m)
        self.n = n
        self._frame = np.zeros((n, dof))
        self._i = 0

    def encode(self, x: Array) -> bytes | None:
        self._frame[self._i] = x
        self._i += 1
        if self._i < self.n:
            return None
        self._i = 0
        coeffs = self.basis @ self._frame  # (m, dof)
        return self.raw.packed16(coeffs.ravel())


class DctDecoder(PlayoutDecoder):
    def __init__(self, raw: RawFormat, n: int, m: int, dof: int, max_queue: int, on_loss: str) -> None:
        super().__init__(dof, max_queue, on_loss)
        self.raw = coefficient_format(raw, n)
        self.basis = dct_basis(n, m)
        self.n = n
        self.m = m
        self.k = n

    def runs(self, payload: bytes) -> list[tuple[Array, int]]:
        coeffs = self.raw.dequantize(unpack16(payload, self.m * self.dof)).reshape(self.m, self.dof)
        frame = self.basis.T @ coeffs  # (n, dof)
        return [(frame[i], 1) for i in range(self.n)]
