"""Direct LDR (Section IV.D): every sample is sent, each reduced on its own.

``none`` ships the raw 16-bit sample; ``cq:BITS`` keeps only the top BITS bits of it, rounding
toward zero so that ``|g_r(t+T)| <= |g_l(t)|`` (eq. 11).  No delay is added.
"""

from __future__ import annotations

import numpy as np

from teleop.control.codecs.base import (
    RAW_BITS,
    Array,
    Encoder,
    PlayoutDecoder,
    RawFormat,
    pack,
    unpack,
    unpack16,
)


class DirectEncoder(Encoder):
    def __init__(self, raw: RawFormat, bits: int) -> None:
        self.raw = raw
        self.bits = bits
        self.shift = 1 << (RAW_BITS - bits)

    def encode(self, x: Array) -> bytes:
        if self.shift == 1:  # none: the raw codes
            return self.raw.packed16(x)
        q16 = self.raw.quantize(x)
        # Division toward zero (astype truncates), not floor: eq. (11) needs |Q(x)| <= |x|.
        q = (q16 / self.shift).astype(np.int64)
        return pack(q, self.bits)


class DirectDecoder(PlayoutDecoder):
    def __init__(self, raw: RawFormat, bits: int, dof: int, max_queue: int, on_loss: str = "zero") -> None:
        super().__init__(dof, max_queue, on_loss)
        self.raw = raw
        self.bits = bits
        self.shift = 1 << (RAW_BITS - bits)

    def parse(self, payload: bytes) -> tuple[Array, int]:
        if self.bits == RAW_BITS:
            return self.raw.dequantize(unpack16(payload, self.dof)), 1
        q = unpack(payload, self.bits, self.dof)
        return self.raw.dequantize(q if self.shift == 1 else q * self.shift), 1
