"""Wire format: round trip, and bad input raises WireError only, with an exact message."""

from __future__ import annotations

import contextlib
import zlib

import msgpack
import pytest
from hypothesis import given
from hypothesis import strategies as st

from teleop.session import wire
from teleop.session.wire import Packet, WireError

P = Packet(
    session=7, direction=wire.FORWARD, seq=3, tick=1234, t_us=99, codec_id=2, payload=b"\x01\x02", energy=0.5
)


def test_round_trip() -> None:
    assert wire.decode(wire.encode(P)) == P


@given(
    st.builds(
        Packet,
        session=st.integers(0, 2**32 - 1),
        direction=st.sampled_from([0, 1]),
        seq=st.integers(0, 2**32 - 1),
        tick=st.integers(0, 2**64 - 1),
        t_us=st.integers(0, 2**64 - 1),
        codec_id=st.integers(0, 255),
        payload=st.binary(max_size=64),
        energy=st.floats(0, 1e300),
    )
)
def test_round_trip_any(p: Packet) -> None:
    assert wire.decode(wire.encode(p)) == p


def test_every_truncation_is_a_wire_error() -> None:
    data = wire.encode(P)
    for cut in range(len(data)):
        with pytest.raises(WireError):
            wire.decode(data[:cut])


@given(st.binary(max_size=80))
def test_garbage_raises_only_wire_error(data: bytes) -> None:
    with contextlib.suppress(WireError):  # anything else fails the test
        wire.decode(data)


def _fields(**change: object) -> bytes:
    f: list[object] = [b"TW", 1, 7, 0, 3, 1234, 99, 2, b"\x01", 0.5]
    names = [
        "magic",
        "version",
        "session",
        "direction",
        "seq",
        "tick",
        "t_us",
        "codec_id",
        "payload",
        "energy",
    ]
    for k, v in change.items():
        f[names.index(k)] = v
    return _crc(msgpack.packb(f, use_bin_type=True))


def _crc(body: bytes) -> bytes:
    return body + zlib.crc32(body).to_bytes(4, "little")


@pytest.mark.parametrize(
    "data,msg",
    [
        (b"\x01\x02", "packet too short: 2 bytes"),
        (b"\x9a\x00\x00\x00\x00\x00", "CRC-32 mismatch"),
        (_crc(b"\xc1"), "not msgpack"),
        (_crc(msgpack.packb({"a": 1})), "must be a msgpack array, got dict"),
        (_crc(msgpack.packb([1, 2, 3])), "must have 10 fields, got 3"),
        (_fields(magic=b"XX"), "bad magic b'XX'"),
        (_fields(version=2), "unsupported version 2, expected 1"),
        (_fields(direction=5), "direction must be 0 or 1, got 5"),
        (_fields(session=-1), "field session must be an unsigned integer"),
        (_fields(seq=2**33), "field seq must be an unsigned integer"),
        (_fields(tick="x"), "field tick must be an unsigned integer"),
        (_fields(payload="text"), "field payload must be bin, got str"),
        (_fields(energy=float("nan")), "field energy must be a finite float >= 0"),
        (_fields(energy=-1.0), "field energy must be a finite float >= 0"),
        (_fields(codec_id=300), "field codec_id must be an unsigned integer <= 255"),
    ],
)
def test_exact_messages(data: bytes, msg: str) -> None:
    with pytest.raises(WireError, match=msg.replace("(", r"\(").replace("[", r"\[")):
        wire.decode(data)


@pytest.mark.parametrize("bit", range(0, 8 * 40, 7))
def test_any_flipped_bit_is_detected(bit: int) -> None:
    data = bytearray(wire.encode(P))
    data[bit // 8 % len(data)] ^= 1 << (bit % 8)
    with pytest.raises(WireError):
        wire.decode(bytes(data))


def test_packet_overhead_is_small() -> None:
    """The header is what sets wire-level compression for sparse codecs; keep an eye on it."""
    assert len(wire.encode(P)) - len(P.payload) <= 36
