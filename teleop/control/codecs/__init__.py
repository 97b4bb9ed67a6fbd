"""LDR codecs on wave variables, chosen by a spec (``none``, ``ids:K``, ``eds:K``, ``cq:BITS``,
``pd:PCT``, ``pdp:PCT``, ``pdr:PCT``, ``dct:N:M``; every grammar, preset and named form in
:mod:`teleop.control.codecs.spec`, which parses a spec once into a :class:`CodecSpec`;
:func:`make_codec` turns one into a :class:`Codec` without parsing it again).

Each codec is an encoder/decoder pair that enforces its class's passivity condition:

==========  ==============  ===========================================  ==================
spec        class           passivity condition                          added delay
==========  ==============  ===========================================  ==================
none        direct          raw 16-bit, rounded toward zero (eq. 11)     none
cq:BITS     direct          eq. (11), rounding toward zero               none
ids:K       interpolative   eq. (8), frame mean (Cauchy-Schwarz)         one frame
eds:K       extrapolative   eq. (10), budgeted hold                      none
pd:PCT      deadband        Weber band; budgeted hold (sender + guard)   none
pdp:PCT     deadband        predictive band; budgeted extrapolation      none
pdr:PCT     deadband        as pdp, predicting the reflection (eq. 3)    none
dct:N:M     frequency       eq. (8) by Parseval, M of N DCT-II coeffs    one frame
==========  ==============  ===========================================  ==================

``rate_limited`` wraps none of them: a rate cap (``teleop.control.ratecap``) sits in the node, in front of
any encoder, and tells it with :meth:`Encoder.cancel` when a payload was held back.

Neither side reads a clock: an encoder is called once per tick, a decoder yields once per tick.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

from teleop.control.codecs.base import (
    POWER_CODEC_BASE,
    RAW_BITS,
    Array,
    CodecError,
    Encoder,
    PlayoutDecoder,
    RawFormat,
    packed_size,
)
from teleop.control.codecs.deadband import DeadbandDecoder, DeadbandEncoder
from teleop.control.codecs.direct import DirectDecoder, DirectEncoder
from teleop.control.codecs.extrapolative import EdsDecoder, EdsEncoder
from teleop.control.codecs.frequency import DctDecoder, DctEncoder
from teleop.control.codecs.interpolative import IdsDecoder, IdsEncoder
from teleop.control.codecs.reflective import ReflectiveDecoder, ReflectiveEncoder
from teleop.control.codecs.spec import (
    ACCEPTED,
    GRAMMARS,
    MAX_BAND_PCT,
    MAX_K,
    MAX_RESERVE_PCT,
    PRESETS,
    CodecSpec,
    expand,
)

__all__ = [
    "ACCEPTED",
    "CODECS",
    "DEFAULT_FULL_SCALE",
    "GRAMMARS",
    "MAX_BAND_PCT",
    "MAX_K",
    "MAX_RESERVE_PCT",
    "PRESETS",
    "Array",
    "Codec",
    "CodecError",
    "CodecSpec",
    "Encoder",
    "PlayoutDecoder",
    "RawFormat",
    "expand",
    "make_codec",
]

#: Default full scale of the raw 16-bit wave format, in sqrt(W).  Section V's signals stay within
#: about +-2 (b = 1, unit velocity step); the headroom keeps the protocol scenario unsaturated.
DEFAULT_FULL_SCALE = 16.0


@dataclass(frozen=True)
class Codec:
    """A parsed codec spec bound to a DoF count and a raw format: a factory of encoder/decoder."""

    spec: CodecSpec
    name: str
    codec_id: int
    klass: str
    dof: int
    raw: RawFormat
    k: int  # ticks covered by one payload
    bits: int  # bits per value on the wire
    make_encoder: Callable[[], Encoder]
    make_decoder: Callable[[int, str], PlayoutDecoder]
    values: int = 1  # values per DoF in one payload (pdp: value and slope; dct: M coefficients)
    event_based: bool = False  # sends when the signal asks (deadband): k is its longest interval
    extra_bytes: int = 0  # beyond the values (pdr's cKAPPA: the lag it measured, 16 bits)

    @property
    def payload_bytes(self) -> int:
        return packed_size(self.dof * self.values, self.bits) + self.extra_bytes

    @property
    def raw_bytes_per_tick(self) -> int:
        """Bytes of the uncompressed baseline: every tick's raw 16-bit sample."""
        return packed_size(self.dof, RAW_BITS)

    @property
    def nominal_compression(self) -> float:
        """c of eq. (9) in bytes: baseline bytes over K ticks / one payload (for a deadband codec,
        the least it compresses: one payload per heartbeat)."""
        return self.k * self.raw_bytes_per_tick / self.payload_bytes

    @property
    def added_delay_ticks(self) -> int:
        """Delay the codec adds by construction (frame-based only)."""
        return self.k - 1 if self.klass in ("interpolative", "frequency") else 0

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


Factory = Callable[[CodecSpec, int, float], Codec]


def _none(spec: CodecSpec, dof: int, fs: float) -> Codec:
    raw = RawFormat(fs)
    return Codec(
        spec,
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


def _ids(spec: CodecSpec, dof: int, fs: float) -> Codec:
    k, raw = int(spec.values["K"]), RawFormat(fs)
    return Codec(
        spec,
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


def _eds(spec: CodecSpec, dof: int, fs: float) -> Codec:
    k, raw = int(spec.values["K"]), RawFormat(fs)
    return Codec(
        spec,
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


def _cq(spec: CodecSpec, dof: int, fs: float) -> Codec:
    bits = int(spec.values["BITS"])
    try:
        raw = RawFormat(spec.values.get("RANGE", fs))
    except CodecError as e:
        raise CodecError(f"codec {spec!r}: {e}") from None
    return Codec(
        spec,
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


def _deadband(spec: CodecSpec, dof: int, fs: float) -> Codec:
    """``pd`` and ``pdp`` (``teleop.control.codecs.deadband``)."""
    predictive = spec.name == "pdp"
    pct, hb = spec.values["PCT"], int(spec.values["MAXMS"])
    raw = RawFormat(fs)
    # MAXMS is counted in ticks, which are ms at the default 1 kHz (a codec does not know dt);
    # the node's link supervision reads k, so it stays consistent at any rate.
    return Codec(
        spec,
        spec.name,
        5 if predictive else 4,
        "deadband",
        dof,
        raw,
        hb,
        RAW_BITS,
        lambda: DeadbandEncoder(raw, dof, pct, hb, predictive),
        lambda q, o: DeadbandDecoder(raw, dof, predictive, q, o),
        values=2 if predictive else 1,
        event_based=True,
    )


def _pdr(spec: CodecSpec, dof: int, fs: float) -> Codec:
    """``pdr``: pdp's payload, the reflection-aware receiver, per-direction settings and optional
    self-credit (``teleop.control.codecs.reflective``)."""
    v = spec.values
    pct, hb, bpct, fr, br = v["PCT"], int(v["MAXMS"]), v["BPCT"], v["FR"], v["BR"]
    credit = v["KAPPA"] / 100.0 if "KAPPA" in v else None
    raw = RawFormat(fs)
    return Codec(
        spec,
        "pdr",
        7,
        "deadband",
        dof,
        raw,
        hb,
        RAW_BITS,
        lambda: ReflectiveEncoder(raw, dof, pct, hb, bpct, (fr, br), credit),
        lambda q, o: ReflectiveDecoder(raw, dof, q, o, credit is not None),
        values=2,
        event_based=True,
        extra_bytes=2 if credit is not None else 0,
    )


def _dct(spec: CodecSpec, dof: int, fs: float) -> Codec:
    n, m = int(spec.values["N"]), int(spec.values["M"])
    raw = RawFormat(fs)
    return Codec(
        spec,
        "dct",
        6,
        "frequency",
        dof,
        raw,
        n,
        RAW_BITS,
        lambda: DctEncoder(raw, n, m, dof),
        lambda q, o: DctDecoder(raw, n, m, dof, q, o),
        values=m,
    )


#: name -> factory(spec, dof, full_scale): one per grammar of ``teleop.control.codecs.spec.GRAMMARS``.
CODECS: dict[str, Factory] = {
    "none": _none,
    "ids": _ids,
    "eds": _eds,
    "cq": _cq,
    "pd": _deadband,
    "pdp": _deadband,
    "pdr": _pdr,
    "dct": _dct,
}


#: The codecs that make sense on power variables (TDPA): a frequency codec's frame of delay and
#: Parseval bound buy nothing there.
POWER_CODECS = ("none", "cq", "ids", "eds", "pd", "pdp", "pdr")


def _powered(enc: Encoder) -> Encoder:
    enc.power = True
    return enc


def on_power_variable(c: Codec) -> Codec:
    """The same codec on a power variable (TDPA): its wave-energy rules off (``Encoder.power``) and
    its id moved to ``POWER_CODEC_BASE + id`` (``teleop.session.wire``), so a wave peer refuses the payload
    as another codec instead of playing a velocity as a wave."""
    if c.name not in POWER_CODECS:
        raise CodecError(
            f"codec {c.spec!r} is not available with --passivity tdpa (power variables); "
            f"accepted there: {', '.join(POWER_CODECS)}"
        )
    make = c.make_encoder
    return dataclasses.replace(
        c, codec_id=POWER_CODEC_BASE + c.codec_id, make_encoder=lambda: _powered(make())
    )


def build(spec: CodecSpec, dof: int, full_scale: float, power: bool = False) -> Codec:
    """``spec`` bound to ``dof`` values of ``full_scale`` ; ``power``: for a
    power variable under TDPA (:func:`on_power_variable`)."""
    if dof < 1:
        raise CodecError(f"dof must be >= 1, got {dof}")
    c = CODECS[spec.name](spec, dof, full_scale)
    return on_power_variable(c) if power else c


def make_codec(
    spec: str | CodecSpec, dof: int = 1, full_scale: float = DEFAULT_FULL_SCALE, power: bool = False
) -> Codec:
    """Parse ``spec`` (unless it is a :class:`CodecSpec` already) and bind it; raises
    :class:`CodecError` listing what is accepted.  A parsed spec is not parsed again."""
    return build(CodecSpec.parse(spec), dof, full_scale, power)
