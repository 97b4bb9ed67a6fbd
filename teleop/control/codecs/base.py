"""Shared pieces of every LDR codec: the raw 16-bit sample format, bit packing, playout.

Why a raw 16-bit format: the paper's baseline is a 16-bit quantised stream (Section V.C), and
compression c:1 is counted against it.  Every codec therefore ships values in that format (or, for
``cq``, fewer bits of it), so the payload bytes on the wire are exactly what eq. (9) predicts.

Every conversion from a real value to integers rounds toward zero and saturates, so
``|decoded| <= |original|`` per DoF: eq. (11) holds for the format itself, and the energy
conditions (8) and (10) are never broken by the representation.
"""

from __future__ import annotations

import importlib
import sys
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from teleop.errors import LocalError

#: The two directions of a channel (the wire's direction bit): operator -> teleoperator, and back.
#: Defined here, not in ``teleop.session.wire``, because a codec needs them and sits below the wire.
FORWARD = 0
BACKWARD = 1
#: Codec ids from here on carry a power variable (TDPA): ``POWER_CODEC_BASE + id`` of the codec.
POWER_CODEC_BASE = 16

#: The clip ufunc itself: ``np.clip`` wraps it in Python argument handling that costs several times
#: the ufunc on a few DoF, and it is not exported (``numpy._core.umath`` from numpy 2, ``numpy.core``
#: before).
_clip: np.ufunc = importlib.import_module(
    "numpy._core.umath" if int(np.__version__.split(".")[0]) >= 2 else "numpy.core.umath"
).clip

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

RAW_BITS = 16

#: The packed dtypes as objects: a dtype given as a string is parsed again on every call (measured
#: about twice the cost of ``np.frombuffer`` itself on a few DoF).
_I2, _I1, _I8 = np.dtype("<i2"), np.dtype("i1"), np.dtype(np.int64)


class CodecError(LocalError):
    """A codec spec is invalid, or a payload does not match its codec."""


@dataclass(frozen=True)
class RawFormat:
    """Signed fixed point over ``[-full_scale, full_scale]`` with ``bits`` bits, symmetric."""

    full_scale: float
    bits: int = RAW_BITS

    def __post_init__(self) -> None:
        if not np.isfinite(self.full_scale) or self.full_scale <= 0:
            raise CodecError(f"full scale (range) must be finite and > 0, got {self.full_scale!r}")
        if not 2 <= self.bits <= RAW_BITS:
            raise CodecError(f"bits must be in 2..{RAW_BITS}, got {self.bits}")
        # A step below the smallest normal float (a subnormal range such as 5e-324) has no finite
        # inverse: every code would be NaN (0 * inf), so such a range is refused, not played.
        lowest = self.max_code * sys.float_info.min
        if self.full_scale < lowest:
            raise CodecError(
                f"full scale (range) must be at least {lowest:.3g} for {self.bits}-bit codes "
                f"(a step of at least the smallest normal float), got {self.full_scale!r}"
            )
        # Computed once (the 1 kHz path reads them every tick; the properties compute them anew).
        object.__setattr__(self, "_inv_step", self.max_code / self.full_scale)
        object.__setattr__(self, "_step", self.step)
        object.__setattr__(self, "_max_code_f", float(self.max_code))

    _inv_step: float = field(init=False, repr=False, compare=False, default=0.0)
    _step: float = field(init=False, repr=False, compare=False, default=0.0)
    _max_code_f: float = field(init=False, repr=False, compare=False, default=0.0)
    _shaped: dict[tuple[int, ...], tuple[Array, Array, Array, Array]] = field(
        init=False, repr=False, compare=False, default_factory=dict
    )

    def _constants(self, shape: tuple[int, ...]) -> tuple[Array, Array, Array, Array]:
        """``1/step``, ``-max_code``, ``max_code`` and ``step`` as arrays of ``shape``, made once per
        shape.  An array times an array of equal values gives the same IEEE products as times the
        Python float, at about half the cost on a few DoF (numpy converts a scalar on every call)."""
        c = self._shaped.get(shape)
        if c is None:
            m = self._max_code_f
            full = np.full
            c = self._shaped[shape] = (
                full(shape, self._inv_step),
                full(shape, -m),
                full(shape, m),
                full(shape, self._step),
            )
        return c

    @property
    def max_code(self) -> int:
        return (1 << (self.bits - 1)) - 1

    @property
    def step(self) -> float:
        return self.full_scale / self.max_code

    def quantize(self, x: Array, dtype: np.dtype[Any] = _I8) -> IntArray:
        """Round toward zero and saturate: ``|dequantize(quantize(x))| <= |x|`` (eq. 11).  ``dtype``:
        the codes' integer type (int16 holds any code of at most 16 bits: :meth:`packed16`)."""
        inv, lo, hi, _ = self._constants(x.shape)
        # astype truncates toward zero; saturating first keeps |code| <= max_code.  The clip ufunc
        # is minimum(maximum(., -m), m) element for element (NaN included), in one call.
        q: IntArray = _clip(x * inv, lo, hi).astype(dtype)
        return q

    def packed16(self, x: Array) -> bytes:
        """``pack(quantize(x), 16)`` with one cast, float to int16, instead of two through int64 (the
        same codes: each is saturated to at most 16 bits first).  On every 16-bit codec's send."""
        return self.quantize(x, _I2).tobytes()

    def dequantize(self, q: npt.NDArray[np.signedinteger[Any]]) -> Array:
        # The integer array times the float64 steps: numpy converts each code to float64 (exactly,
        # as astype(float64) would) inside the multiply, one call instead of two.
        out: Array = q * self._constants(q.shape)[3]
        return out


def pack(q: IntArray, bits: int) -> bytes:
    """Pack signed integers of ``bits`` bits each, little-endian bit order, zero-padded."""
    if bits == 16:
        return q.astype(_I2).tobytes()
    if bits == 8:
        return q.astype(_I1).tobytes()
    mask = (1 << bits) - 1
    acc = 0
    for i, v in enumerate(q.tolist()):
        acc |= (int(v) & mask) << (i * bits)
    return acc.to_bytes(packed_size(len(q), bits), "little")


def _check_length(data: bytes, bits: int, n: int) -> None:
    want = packed_size(n, bits)
    if len(data) != want:
        raise CodecError(f"payload has {len(data)} bytes, expected {want} ({n} values of {bits} bits)")


def unpack16(data: bytes, n: int) -> npt.NDArray[np.int16]:
    """:func:`unpack` of ``n`` raw 16-bit codes, left as int16 (a read-only view of ``data``): what
    :meth:`RawFormat.dequantize` takes, as int16 converts to float64 exactly, as int64 does (one
    cast fewer per payload, on the receive path of every 16-bit codec)."""
    _check_length(data, 16, n)
    return np.frombuffer(data, _I2)


def unpack(data: bytes, bits: int, n: int) -> IntArray:
    """Inverse of :func:`pack`; raises :class:`CodecError` on a wrong length."""
    _check_length(data, bits, n)
    if bits == 16:
        return np.frombuffer(data, _I2).astype(np.int64)
    if bits == 8:
        return np.frombuffer(data, _I1).astype(np.int64)
    acc = int.from_bytes(data, "little")
    mask = (1 << bits) - 1
    sign = 1 << (bits - 1)
    out = np.empty(n, dtype=np.int64)
    for i in range(n):
        v = (acc >> (i * bits)) & mask
        out[i] = v - (1 << bits) if v & sign else v
    if acc >> (n * bits):
        raise CodecError("payload has non-zero padding bits")
    return out


def packed_size(n: int, bits: int) -> int:
    return (n * bits + 7) // 8


CONCEAL_FADE = 0.95  # per tick of a gap beyond one payload: down to 5% after about 60 ticks


class Encoder:
    """Turns one wave sample per tick into a payload, or ``None`` when it does not transmit.

    ``phase`` (ticks) shifts the send ticks of a periodic sparse encoder (eDS, iDS) within its
    period: it sends on calls ``n`` with ``(n - phase) % K == 0``.  The teleoperator sets it to the
    forward direction's playout offset (issue 13, send phase), so that it samples right after the
    operator's payload took effect, in the real run exactly as in ``teleop sim``.
    """

    phase = 0
    #: On a power variable (TDPA, ``teleop.session.node``): the wave-energy rules of eq. (8)/(10) do not
    #: apply (``x . x`` is no energy there); the TDPA controller keeps the channel passive instead.
    power = False
    #: Set by a TDPA node before ``encode`` when its unreported input energy is due: an event-based
    #: encoder sends this tick (an energy-triggered update); periodic ones ignore it.
    urgent = False
    #: J of the energy this side sent that the encoder credited its own guard with and withholds from
    #: its reports (cumulative; ``pdr``'s self-credit, ``teleop.control.passivity.EnergyGuard.credit``): the
    #: node subtracts it from its energy reports.
    withheld = 0.0

    def encode(self, x: Array) -> bytes | None:  # pragma: no cover - interface
        raise NotImplementedError

    def cancel(self) -> None:
        """The payload the last ``encode`` returned was not sent (a rate cap held it back).

        Codecs whose sender models the receiver (eDS, the deadbands) undo what they assumed it
        plays; for the others the receiver just misses that payload, as on a loss.
        """


class PhasedSchedule:
    """When a periodic sparse encoder sends: every ``k`` calls, shifted by ``phase``.

    A change of ``phase`` moves the *next* send by the change (wrapped to within half a period), so
    a phase that moves never makes two sends closer than one call, nor one interval longer than
    ``2k - 1``: one payload interval is shortened or stretched, the rest keep the period.
    """

    __slots__ = ("_next", "_phase", "k", "n")

    def __init__(self, k: int) -> None:
        self.k = k
        self.n = 0  # calls so far
        self._next = 1  # the call that sends next (the first call, as before any phase is known)
        self._phase = 0

    def due(self, phase: int) -> bool:
        """Count one call; whether it sends."""
        self.n += 1
        if phase != self._phase:
            half = self.k // 2
            shift = (phase - self._phase + half) % self.k - half
            self._next = max(self._next + shift, self.n)
            self._phase = phase
        if self.n < self._next:
            return False
        self._next = self.n + self.k
        return True


class _Run:
    """``value`` still to be played for ``remaining`` ticks."""

    __slots__ = ("remaining", "value")

    def __init__(self, value: Array, remaining: int) -> None:
        self.value = value
        self.remaining = remaining


class PlayoutDecoder:
    """Receives payloads, yields one sample per tick from a playout queue.

    A payload becomes ``(value, count)``: play ``value`` for ``count`` ticks.  When the queue runs
    dry the output is zero, never a held value: holding would replay energy that was never sent
    (in wave variables hold-last-sample generates energy).  When it grows beyond ``max_queue`` ticks
    (a burst after a stall) the oldest samples are dropped, which only removes energy.
    """

    def __init__(self, dof: int, max_queue: int, on_loss: str = "zero") -> None:
        if on_loss not in ("zero", "hold", "conceal"):
            raise CodecError(f"on_loss must be 'zero', 'hold' or 'conceal', got {on_loss!r}")
        self.dof = dof
        self.max_queue = max_queue
        self.on_loss = on_loss
        self._gap = 0  # ticks since the queue ran dry
        self._queue: deque[_Run] = deque()
        self._queued = 0
        self._zero = np.zeros(dof)
        self._last = self._zero
        self.underruns = 0
        self.dropped_samples = 0

    def parse(self, payload: bytes) -> tuple[Array, int]:  # pragma: no cover - interface
        raise NotImplementedError

    def runs(self, payload: bytes) -> list[tuple[Array, int]]:
        """The ``(value, count)`` runs a payload plays: one for a held value, N for a frame."""
        return [self.parse(payload)]

    def push(self, payload: bytes) -> None:
        """Queue a payload; a malformed one raises :class:`CodecError` and changes nothing."""
        for value, count in self.runs(payload):
            self._queue.append(_Run(value, count))
            self._queued += count
        while self._queued > self.max_queue:
            head = self._queue[0]
            excess = min(self._queued - self.max_queue, head.remaining)
            head.remaining -= excess
            self._queued -= excess
            self.dropped_samples += excess
            if head.remaining == 0:
                self._queue.popleft()

    def clear(self) -> None:
        """Forget everything queued (the sender was replaced); only removes energy."""
        self.dropped_samples += self._queued
        self._queue.clear()
        self._queued = 0
        self._last = self._zero

    @property
    def queued(self) -> int:
        """Ticks of signal waiting to be played."""
        return self._queued

    def next(self) -> Array:
        """The sample to play this tick (zero on underrun)."""
        if not self._queue:
            self.underruns += 1
            # "hold" repeats the last value and "conceal" fades it out (CONCEAL_FADE per tick): both
            # generate energy unless a passivity controller bounds them (teleop.control.passivity), which
            # plays them only within the budget; "zero" is passive by itself.
            if self.on_loss == "zero":
                return self._zero
            self._gap += 1
            if self.on_loss == "hold":
                return self._last
            # One payload interval of the gap is a lost payload: held in full; beyond, it fades.
            over = self._gap - getattr(self, "k", 1)
            return self._last if over <= 0 else self._last * (CONCEAL_FADE**over)
        self._gap = 0
        head = self._queue[0]
        head.remaining -= 1
        self._queued -= 1
        if head.remaining == 0:
            self._queue.popleft()
        self._last = head.value
        return head.value
