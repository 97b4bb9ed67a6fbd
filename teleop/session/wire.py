"""Versioned msgpack packet carrying one codec payload between the two nodes.

A packet is a msgpack array (arrays, not maps: field names would cost more than the payload)
followed by a CRC-32 of the array's bytes (zlib/IEEE, 4 bytes little-endian)::

    msgpack([magic, version, session, direction, seq, tick, t_us, codec_id, payload, energy]) + crc32

On the wire this body travels inside the authenticated envelope of ``teleop.session.auth``, whose tag
catches any corruption (the impairment shim's ``corrupt`` included: such datagrams are counted as
``security.rejected``).  The CRC predates the envelope; it still guards a body that is handled
outside one (a log, a test) and costs 4 bytes.

=========  =========  ==============================================================
field      msgpack    meaning
=========  =========  ==============================================================
magic      bin "TW"   identifies teleop packets
version    uint       ``VERSION`` (1); another version is rejected
session    uint32     session id agreed in the handshake; others are dropped
direction  uint       0 forward (operator -> TO, wave g), 1 backward (TO -> operator, wave h)
seq        uint32     packets this sender's node produced before this one, from 0 (the shim may drop some)
tick       uint64     sender's loop tick at which the payload was produced
t_us       uint64     the tick's session time, ``round(tick * dt * 1e6)`` microseconds (not a clock)
codec_id   uint       0 none, 1 ids, 2 eds, 3 cq, 4 pd, 5 pdp, 6 dct, 7 pdr
payload    bin        the codec's bytes (see ``teleop.control.codecs``)
energy     float      sender's cumulative transmitted wave energy, J (eq. 4-5); float32/64 only
=========  =========  ==============================================================

Under ``--passivity tdpa`` (PROTOCOL.md section 8) the layout is the same; ``codec_id`` is
``POWER_CODEC_BASE + id``, the payload carries a power variable (velocity forward, force back) and
``energy`` the sender's cumulative TDPA input energy ``E_in``, J (``teleop.control.passivity``).

``decode`` raises :class:`WireError` (and nothing else) with an exact message for any input that
is not such a packet; transports catch it, count the packet as malformed and drop it.
"""

from __future__ import annotations

import math
import zlib
from typing import NamedTuple

import msgpack
import numpy as np
import numpy.typing as npt

from teleop import limits
from teleop.control.codecs import base as codec_base
from teleop.errors import RemoteError
from teleop.session import auth

MAGIC = b"TW"
VERSION = 1
# The direction bit and the power-codec id base are the wire's; the codecs (below it) define them.
FORWARD = codec_base.FORWARD
BACKWARD = codec_base.BACKWARD
POWER_CODEC_BASE = codec_base.POWER_CODEC_BASE
DIRECTIONS = ("forward", "backward")
_U32 = 0xFFFFFFFF
_U64 = 0xFFFFFFFFFFFFFFFF


class WireError(RemoteError):
    """Bytes that are not a valid teleop packet."""


class Packet(NamedTuple):
    """One parsed (or to be encoded) packet.  Immutable; a named tuple, not a frozen dataclass: one is
    made per datagram each way on the 1 kHz path, and a frozen dataclass's ``__init__`` sets each of
    its eight fields through ``object.__setattr__`` (several times the cost)."""

    session: int
    direction: int
    seq: int
    tick: int
    t_us: int
    codec_id: int
    payload: bytes
    energy: float = 0.0


#: One packer for every packet: ``msgpack.packb`` builds a new one per call, which is most of its
#: cost on the 1 kHz path; same options, so the same bytes.  The C packer's ``pack`` holds the GIL
#: from start to end, so threads cannot interleave in its buffer, and it empties the buffer when a
#: value does not fit (the next packet starts clean).
_PACKER = msgpack.Packer(use_bin_type=True)


def encode(p: Packet) -> bytes:
    body: bytes = _PACKER.pack(
        [
            MAGIC,
            VERSION,
            p.session,
            p.direction,
            p.seq,
            p.tick,
            p.t_us,
            p.codec_id,
            p.payload,
            float(p.energy),
        ]
    )
    return body + zlib.crc32(body).to_bytes(4, "little")


def uint_size(v: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """Bytes msgpack takes for unsigned integers ``v`` (fixint, uint8, uint16, uint32, uint64)."""
    a = np.asarray(v, dtype=np.uint64)
    return np.select([a < 128, a < 256, a < 65536, a < 2**32], [1, 2, 3, 5], 9).astype(np.int64)


def packet_size(
    session: int, seq: npt.ArrayLike, tick: npt.ArrayLike, t_us: npt.ArrayLike, payload_len: int
) -> npt.NDArray[np.int64]:
    """Bytes of ``encode(Packet(session, d, seq, tick, t_us, codec_id < 128, payload, energy))``,
    vectorised over ``seq``/``tick``/``t_us``: the uncompressed baseline is counted without
    encoding a packet per tick (a test checks it against :func:`encode`)."""
    bin_header = 2 if payload_len < 256 else 3 if payload_len < 65536 else 5
    fixed = 1 + (2 + len(MAGIC)) + 1 + 1 + 1 + bin_header + payload_len + 9 + 4  # array, magic, version,
    # direction, codec_id, payload, float64 energy, CRC-32
    return fixed + uint_size(session) + uint_size(seq) + uint_size(tick) + uint_size(t_us)


def _usize(v: int) -> int:
    return 1 if v < 128 else 2 if v < 256 else 3 if v < 65536 else 5 if v < 2**32 else 9


def encoded_size(pkt: Packet) -> int:
    """``len(encode(pkt))`` without encoding it (codec_id < 128): :func:`packet_size` for one packet,
    in plain integers, so a rate cap can size a datagram on the 1 kHz path before it is built."""
    n = len(pkt.payload)
    bin_header = 2 if n < 256 else 3 if n < 65536 else 5
    fixed = 1 + (2 + len(MAGIC)) + 1 + 1 + 1 + bin_header + n + 9 + 4
    return fixed + _usize(pkt.session) + _usize(pkt.seq) + _usize(pkt.tick) + _usize(pkt.t_us)


def _uint(name: str, v: object, hi: int) -> int:
    if type(v) is not int or not 0 <= v <= hi:
        raise WireError(f"field {name} must be an unsigned integer <= {hi}, got {v!r}")
    return v


def decode(data: bytes) -> Packet:
    """Parse one packet; raises :class:`WireError` only."""
    if len(data) < 5:
        raise WireError(f"packet too short: {len(data)} bytes")
    body = data[:-4]
    if zlib.crc32(body) != int.from_bytes(data[-4:], "little"):
        raise WireError("CRC-32 mismatch: the packet was corrupted")
    try:
        obj = msgpack.unpackb(body, raw=False, use_list=True, strict_map_key=True)
    except Exception as e:  # msgpack raises several unrelated types for garbage input
        raise WireError(f"not msgpack: {type(e).__name__}: {e}") from None
    if not isinstance(obj, list):
        raise WireError(f"packet must be a msgpack array, got {type(obj).__name__}")
    if len(obj) != 10:
        raise WireError(f"packet must have 10 fields, got {len(obj)}")
    magic, version, session, direction, seq, tick, t_us, codec_id, payload, energy = obj
    if magic != MAGIC:
        raise WireError(f"bad magic {magic!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise WireError(f"unsupported version {version!r}, expected {VERSION}")
    if direction not in (FORWARD, BACKWARD) or type(direction) is not int:
        raise WireError(f"field direction must be 0 or 1, got {direction!r}")
    if type(payload) is not bytes:
        raise WireError(f"field payload must be bin, got {type(payload).__name__}")
    if type(energy) is not float or not math.isfinite(energy) or energy < 0.0:
        raise WireError(f"field energy must be a finite float >= 0, got {energy!r}")
    # One test of every integer field for the 1 kHz path; on failure, _uint says which and why.
    if not (
        type(session) is type(seq) is type(tick) is type(t_us) is type(codec_id) is int
        and 0 <= session <= _U32
        and 0 <= seq <= _U32
        and 0 <= tick <= _U64
        and 0 <= t_us <= _U64
        and 0 <= codec_id <= 255
    ):
        for name, v, hi in (
            ("session", session, _U32),
            ("seq", seq, _U32),
            ("tick", tick, _U64),
            ("t_us", t_us, _U64),
            ("codec_id", codec_id, 255),
        ):
            _uint(name, v, hi)
    return Packet(session, direction, seq, tick, t_us, codec_id, payload, energy)


#: The largest codec payload any session can send: ``teleop.limits.MAX_DOF`` DoF of the codec with
#: the most values per payload (``dct:N:N`` at the longest frame), raw 16-bit values.
# (Not imported from teleop.control.codecs, which imports this module: dct's longest frame,
# teleop.control.codecs.frequency.MAX_FRAME, of raw 16-bit values; tests/test_input_bounds.py checks it
# against the codec itself.)
_MOST_VALUES_PER_DOF, _RAW_BITS = 1000, 16
MAX_PAYLOAD_BYTES = (limits.MAX_DOF * _MOST_VALUES_PER_DOF * _RAW_BITS + 7) // 8
#: The largest data packet: that payload with every header field at its widest.
MAX_PACKET_BYTES = len(encode(Packet(_U32, BACKWARD, _U32, _U64, _U64, 255, bytes(MAX_PAYLOAD_BYTES))))
#: The largest datagram (or Zenoh sample) of the protocol, authenticated envelope included: data
#: packet or control message.  Transports refuse anything longer by its length alone, before any
#: hashing or parsing (the cost of refusing must be small and flat).
MAX_DATAGRAM_BYTES = max(MAX_PACKET_BYTES, limits.MAX_CONTROL_BYTES) + auth.OVERHEAD
#: The largest handshake-key datagram: a control message in its envelope (hello, welcome, retry, reject).
MAX_HANDSHAKE_DATAGRAM_BYTES = limits.MAX_CONTROL_BYTES + auth.OVERHEAD


def max_session_datagram_bytes(dof: int) -> int:
    """The largest session-key datagram of a session of ``dof`` DoF: a control message, or a data
    packet of the codec with the most values per payload at that DoF.  An endpoint refuses a longer
    one by its length alone, before the MAC (a 64 kB datagram costs 0.2 ms to hash)."""
    payload = (dof * _MOST_VALUES_PER_DOF * _RAW_BITS + 7) // 8
    packet = len(encode(Packet(_U32, BACKWARD, _U32, _U64, _U64, 255, bytes(payload))))
    return max(packet, limits.MAX_CONTROL_BYTES) + auth.OVERHEAD
