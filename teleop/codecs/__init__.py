"""LDR codecs on wave variables, chosen by a spec string (``none``, ``ids:K``, ``eds:K``, ``cq:BITS``).

Each codec is an encoder/decoder pair that enforces its class's passivity condition:

==========  ==============  ===========================================  ==================
spec        class           passivity condition                          added delay
==========  ==============  ===========================================  ==================
none        direct          raw 16-bit, rounded toward zero (eq. 11)     none
cq:BITS     direct          eq. (11), rounding toward zero               none
ids:K       interpolative   eq. (8), frame mean (Cauchy-Schwarz)         one frame
eds:K       extrapolative   eq. (10), budgeted hold                      none
==========  ==============  ===========================================  ==================

Neither side reads a clock: an encoder is called once per tick, a decoder yields once per tick.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from .base import RAW_BITS, Array, CodecError, Encoder, PlayoutDecoder, RawFormat, packed_size
from .direct import DirectDecoder, DirectEncoder
from .extrapolative import EdsDecoder, EdsEncoder
from .interpolative import IdsDecoder, IdsEncoder

__all__ = [
    "CODECS",
    "DEFAULT_FULL_SCALE",
    "Array",
    "Codec",
    "CodecError",
    "Encoder",
    "PlayoutDecoder",
    "RawFormat",
    "make_codec",
]

#: Default full scale of the raw 16-bit wave format, in sqrt(W).  Section V's signals stay within
#: about +-2 (b = 1, unit velocity step); the headroom keeps the protocol scenario unsaturated.
DEFAULT_FULL_SCALE = 16.0

ACCEPTED = (
    "none | ids:K | eds:K | cq:BITS[:RANGE]  "
    f"(K integer >= 1 ticks; BITS integer 2..{RAW_BITS}; RANGE full scale > 0, default session range)"
)


@dataclass(frozen=True)
class Codec:
    """A parsed codec spec bound to a DoF count and a raw format: a factory of encoder/decoder."""

    spec: str
    name: str
    codec_id: int
    klass: str
    dof: int
    raw: RawFormat
    k: int  # ticks covered by one payload
    bits: int  # bits per value on the wire
    make_encoder: Callable[[], Encoder]
    make_decoder: Callable[[int, str], PlayoutDecoder]

    @property
    def payload_bytes(self) -> int:
        return packed_size(self.dof, self.bits)

    @property
    def raw_bytes_per_tick(self) -> int:
        """Bytes of the uncompressed baseline: every tick's raw 16-bit sample."""
        return packed_size(self.dof, RAW_BITS)

    @property
    def nominal_compression(self) -> float:
        """c of eq. (9) in bytes: baseline bytes over K ticks / one payload."""
        return self.k * self.raw_bytes_per_tick / self.payload_bytes

    @property
    def added_delay_ticks(self) -> int:
        """Delay the codec adds by construction (frame-based only)."""
        return self.k - 1 if self.klass == "interpolative" else 0

    def encoder(self) -> Encoder:
        return self.make_encoder()

    def decoder(self, max_queue: int | None = None, on_loss: str = "zero") -> PlayoutDecoder:
        """A decoder whose playout queue holds at most ``max_queue`` ticks.

        The default, K (one payload), is "newest wins": a payload that arrives while an older one
        still has ticks left (jitter, a late packet) replaces the leftover instead of adding its
        latency to the rest of the run.  Dropping only removes energy.  On a constant-delay channel
        the queue is empty whenever a payload arrives, so nothing is ever dropped there.
        """
        return self.make_decoder(max_queue if max_queue is not None else self.k, on_loss)


def _int_param(spec: str, text: str, what: str, lo: int, hi: int | None = None) -> int:
    try:
        v = int(text)
    except ValueError:
        raise CodecError(
            f"codec {spec!r}: {what} must be an integer, got {text!r}; accepted: {ACCEPTED}"
        ) from None
    if v < lo or (hi is not None and v > hi):
        bound = f"in {lo}..{hi}" if hi is not None else f">= {lo}"
        raise CodecError(f"codec {spec!r}: {what} must be {bound}, got {v}; accepted: {ACCEPTED}")
    return v


def _none(spec: str, params: list[str], dof: int, fs: float) -> Codec:
    if params:
        raise CodecError(f"codec {spec!r}: 'none' takes no parameter; accepted: {ACCEPTED}")
    raw = RawFormat(fs)
    return Codec(
        "none",
        "none",
        0,
        "direct",
        dof,
        raw,
        1,
        RAW_BITS,
        lambda: DirectEncoder(raw, RAW_BITS),
        lambda q, o: DirectDecoder(raw, RAW_BITS, dof, q, o),
    )


def _frame(name: str) -> Callable[[str, list[str], int, float], Codec]:
    def make(spec: str, params: list[str], dof: int, fs: float) -> Codec:
        if len(params) != 1:
            raise CodecError(f"codec {spec!r}: '{name}' takes one parameter K; accepted: {ACCEPTED}")
        k = _int_param(spec, params[0], "K", 1)
        raw = RawFormat(fs)
        if name == "ids":
            return Codec(
                f"ids:{k}",
                "ids",
                1,
                "interpolative",
                dof,
                raw,
                k,
                RAW_BITS,
                lambda: IdsEncoder(raw, k, dof),
                lambda q, o: IdsDecoder(raw, k, dof, q, o),
            )
        return Codec(
            f"eds:{k}",
            "eds",
            2,
            "extrapolative",
            dof,
            raw,
            k,
            RAW_BITS,
            lambda: EdsEncoder(raw, k, dof),
            lambda q, o: EdsDecoder(raw, k, dof, q, o),
        )

    return make


def _cq(spec: str, params: list[str], dof: int, fs: float) -> Codec:
    if len(params) not in (1, 2):
        raise CodecError(f"codec {spec!r}: 'cq' takes BITS and an optional RANGE; accepted: {ACCEPTED}")
    bits = _int_param(spec, params[0], "BITS", 2, RAW_BITS)
    if len(params) == 2:
        try:
            fs = float(params[1])
        except ValueError:
            raise CodecError(f"codec {spec!r}: RANGE must be a number, got {params[1]!r}") from None
    try:
        raw = RawFormat(fs)
    except CodecError as e:
        raise CodecError(f"codec {spec!r}: {e}") from None
    canon = f"cq:{bits}" if len(params) == 1 else f"cq:{bits}:{fs:g}"
    return Codec(
        canon,
        "cq",
        3,
        "direct",
        dof,
        raw,
        1,
        bits,
        lambda: DirectEncoder(raw, bits),
        lambda q, o: DirectDecoder(raw, bits, dof, q, o),
    )


#: name -> factory(spec, params, dof, full_scale)
CODECS: dict[str, Callable[[str, list[str], int, float], Codec]] = {
    "none": _none,
    "ids": _frame("ids"),
    "eds": _frame("eds"),
    "cq": _cq,
}


def make_codec(spec: str, dof: int = 1, full_scale: float = DEFAULT_FULL_SCALE) -> Codec:
    """Parse ``spec`` and bind it; raises :class:`CodecError` listing what is accepted."""
    if not isinstance(spec, str) or not spec.strip():
        raise CodecError(f"empty codec spec; accepted: {ACCEPTED}")
    name, *params = spec.strip().split(":")
    factory = CODECS.get(name.lower())
    if factory is None:
        raise CodecError(f"unknown codec {name!r} in {spec!r}; accepted: {ACCEPTED}")
    if dof < 1:
        raise CodecError(f"dof must be >= 1, got {dof}")
    return factory(spec, params, dof, full_scale)
