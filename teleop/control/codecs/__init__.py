"""LDR codecs on wave variables, chosen by a spec string (``none``, ``ids:K``, ``eds:K``, ``cq:BITS``,
``pd:K``, ``pdp:K``, ``pdr:K``, ``dct:N:M``).

Each codec is an encoder/decoder pair that enforces its class's passivity condition:

==========  ==============  ===========================================  ==================
spec        class           passivity condition                          added delay
==========  ==============  ===========================================  ==================
none        direct          raw 16-bit, rounded toward zero (eq. 11)     none
cq:BITS     direct          eq. (11), rounding toward zero               none
ids:K       interpolative   eq. (8), frame mean (Cauchy-Schwarz)         one frame
eds:K       extrapolative   eq. (10), budgeted hold                      none
pd:K        deadband        Weber band; budgeted hold (sender + guard)   none
pdp:K       deadband        predictive band; budgeted extrapolation      none
pdr:K       deadband        as pdp, predicting the reflection (eq. 3)    none
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
from teleop.control.codecs.deadband import DEFAULT_HEARTBEAT_MS, DeadbandDecoder, DeadbandEncoder
from teleop.control.codecs.direct import DirectDecoder, DirectEncoder
from teleop.control.codecs.extrapolative import EdsDecoder, EdsEncoder
from teleop.control.codecs.frequency import MAX_FRAME, DctDecoder, DctEncoder
from teleop.control.codecs.interpolative import IdsDecoder, IdsEncoder
from teleop.control.codecs.reflective import POOL_HOLD_TICKS, ReflectiveDecoder, ReflectiveEncoder

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

MAX_K = 100_000  # ticks (100 s at 1 kHz): any longer frame, horizon or heartbeat is meaningless
MAX_BAND_PCT = 100.0
MAX_RESERVE_PCT = 1000.0  # pdr's FR, BR: the reserve scale of a direction, percent of the default

ACCEPTED = (
    "none | ids:K | eds:K | cq:BITS[:RANGE] | pd:PCT[:MAXMS] | pdp:PCT[:MAXMS] | "
    "pdr:PCT[:MAXMS[:BPCT[:FR:BR[:POOL[:HOLD]]]]] | dct:N:M  "
    f"(K integer 1..{MAX_K} ticks; BITS integer 2..{RAW_BITS}; RANGE full scale > 0, default session "
    f"range; PCT deadband in percent, 0 < PCT <= {MAX_BAND_PCT:g}; MAXMS heartbeat in ms, integer "
    f"1..{MAX_K}, default {DEFAULT_HEARTBEAT_MS}; BPCT pdr's backward band, as PCT, default PCT; "
    f"FR, BR pdr's forward and backward reserve scale in percent, 0..{MAX_RESERVE_PCT:g}, default 100; "
    f"POOL, HOLD pdr's two-port pooling, ticks kept and ticks granted for, 0..{MAX_K}; "
    f"N frame 2..{MAX_FRAME} ticks, M coefficients 1..N)"
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
    values: int = 1  # values per DoF in one payload (pdp: value and slope; dct: M coefficients)
    event_based: bool = False  # sends when the signal asks (deadband): k is its longest interval
    extra_bytes: int = 0  # beyond the values (pdr's POOL: its cumulative grant, a float64)

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
        k = _int_param(spec, params[0], "K", 1, MAX_K)
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


def _deadband(name: str) -> Callable[[str, list[str], int, float], Codec]:
    predictive = name in ("pdp", "pdr")

    def make(spec: str, params: list[str], dof: int, fs: float) -> Codec:
        if name == "pdr" and len(params) in (3, 5, 6, 7):
            return _pdr(spec, params, dof, fs)
        if len(params) not in (1, 2):
            extra = " (pdr: then BPCT, then FR and BR, then POOL and HOLD)" if name == "pdr" else ""
            raise CodecError(
                f"codec {spec!r}: '{name}' takes PCT and an optional MAXMS{extra}; accepted: {ACCEPTED}"
            )
        try:
            pct = float(params[0])
        except ValueError:
            raise CodecError(f"codec {spec!r}: PCT must be a number, got {params[0]!r}") from None
        if not 0 < pct <= MAX_BAND_PCT:
            raise CodecError(f"codec {spec!r}: PCT must be in (0, {MAX_BAND_PCT:g}], got {pct:g}")
        hb = _int_param(spec, params[1], "MAXMS", 1, MAX_K) if len(params) == 2 else DEFAULT_HEARTBEAT_MS
        raw = RawFormat(fs)
        # MAXMS is counted in ticks, which are ms at the default 1 kHz (a codec does not know dt);
        # the node's link supervision reads k, so it stays consistent at any rate.
        canon = f"{name}:{pct:g}" + (f":{hb}" if hb != DEFAULT_HEARTBEAT_MS else "")
        if name == "pdr":  # pdp's payload, the reflection-aware receiver (teleop.control.codecs.reflective)
            return Codec(
                canon,
                name,
                7,
                "deadband",
                dof,
                raw,
                hb,
                RAW_BITS,
                lambda: ReflectiveEncoder(raw, dof, pct, hb),
                lambda q, o: ReflectiveDecoder(raw, dof, q, o),
                values=2,
                event_based=True,
            )
        return Codec(
            canon,
            name,
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

    return make


def _pdr(spec: str, params: list[str], dof: int, fs: float) -> Codec:
    """``pdr:PCT:MAXMS:BPCT[:FR:BR]``: the per-direction settings (``teleop.control.codecs.reflective``)."""
    nums = []
    credit = None
    if len(params) == 6 and params[5][:1].lower() == "c":  # self-credit: cKAPPA, kappa in percent
        try:
            credit = float(params[5][1:]) / 100.0
        except ValueError:
            raise CodecError(f"codec {spec!r}: cKAPPA must be c and a number, got {params[5]!r}") from None
        if not 0.0 <= credit < 1.0:
            raise CodecError(f"codec {spec!r}: KAPPA must be in [0, 100) percent, got {params[5]!r}")
        params = params[:5]
    for what, text in zip(("PCT", "MAXMS", "BPCT", "FR", "BR", "POOL", "HOLD"), params, strict=False):
        if what == "MAXMS":
            nums.append(float(_int_param(spec, text, "MAXMS", 1, MAX_K)))
            continue
        try:
            v = float(text)
        except ValueError:
            raise CodecError(f"codec {spec!r}: {what} must be a number, got {text!r}") from None
        if what in ("PCT", "BPCT") and not 0 < v <= MAX_BAND_PCT:
            raise CodecError(f"codec {spec!r}: {what} must be in (0, {MAX_BAND_PCT:g}], got {v:g}")
        if what in ("FR", "BR") and not 0 <= v <= MAX_RESERVE_PCT:
            raise CodecError(f"codec {spec!r}: {what} must be in [0, {MAX_RESERVE_PCT:g}], got {v:g}")
        if what in ("POOL", "HOLD") and not 0 <= v <= MAX_K:
            raise CodecError(f"codec {spec!r}: {what} must be in [0, {MAX_K}] ticks, got {v:g}")
        nums.append(v)
    pct, hb, bpct = nums[0], int(nums[1]), nums[2]
    fr, br = (nums[3], nums[4]) if len(nums) >= 5 else (100.0, 100.0)
    pool = (nums[5], nums[6] if len(nums) == 7 else POOL_HOLD_TICKS) if len(nums) >= 6 else None
    # Canonical: the shortest form that means the same (pdr:0.8:100:0.8 is pdr:0.8).
    tail = [f"{bpct:g}", f"{fr:g}", f"{br:g}"] if (fr, br) != (100.0, 100.0) or pool else [f"{bpct:g}"]
    if pool is not None:
        tail += [f"{pool[0]:g}", *([f"{pool[1]:g}"] if pool[1] != POOL_HOLD_TICKS else [])]
    if credit is not None:
        tail = [f"{bpct:g}", f"{fr:g}", f"{br:g}", f"c{100.0 * credit:g}"]
    if tail == [f"{pct:g}"]:
        tail = []
    canon = ":".join(["pdr", f"{pct:g}", *([str(hb)] if tail or hb != DEFAULT_HEARTBEAT_MS else []), *tail])
    raw = RawFormat(fs)
    return Codec(
        canon,
        "pdr",
        7,
        "deadband",
        dof,
        raw,
        hb,
        RAW_BITS,
        lambda: ReflectiveEncoder(raw, dof, pct, hb, bpct, (fr, br), pool, credit),
        lambda q, o: ReflectiveDecoder(raw, dof, q, o, pool is not None, credit is not None),
        values=2,
        event_based=True,
        extra_bytes=8 if pool is not None else 2 if credit is not None else 0,
    )


def _dct(spec: str, params: list[str], dof: int, fs: float) -> Codec:
    if len(params) != 2:
        raise CodecError(f"codec {spec!r}: 'dct' takes N and M; accepted: {ACCEPTED}")
    n = _int_param(spec, params[0], "N", 2, MAX_FRAME)
    m = _int_param(spec, params[1], "M", 1, n)
    raw = RawFormat(fs)
    return Codec(
        f"dct:{n}:{m}",
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


#: name -> factory(spec, params, dof, full_scale)
CODECS: dict[str, Callable[[str, list[str], int, float], Codec]] = {
    "none": _none,
    "ids": _frame("ids"),
    "eds": _frame("eds"),
    "cq": _cq,
    "pd": _deadband("pd"),
    "pdp": _deadband("pdp"),
    "pdr": _deadband("pdr"),
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


def make_codec(spec: str, dof: int = 1, full_scale: float = DEFAULT_FULL_SCALE, power: bool = False) -> Codec:
    """Parse ``spec`` and bind it; raises :class:`CodecError` listing what is accepted.

    ``power``: for a power variable under TDPA (:func:`on_power_variable`)."""
    if not isinstance(spec, str) or not spec.strip():
        raise CodecError(f"empty codec spec; accepted: {ACCEPTED}")
    name, *params = spec.strip().split(":")
    factory = CODECS.get(name.lower())
    if factory is None:
        raise CodecError(f"unknown codec {name!r} in {spec!r}; accepted: {ACCEPTED}")
    if dof < 1:
        raise CodecError(f"dof must be >= 1, got {dof}")
    c = factory(spec, params, dof, full_scale)
    return on_power_variable(c) if power else c
