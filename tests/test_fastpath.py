"""The 1 kHz path's cheaper forms compute exactly what the forms they replaced did (issue 22).

Each test sets a rewritten step against the original expression on arbitrary inputs, bit for bit:
the sim goldens (``tests/test_sim_golden.py``) cover the whole run, these the edge cases a run may
not reach (saturation, NaN, infinities, negative zero, every payload length).
"""

from __future__ import annotations

import math
import zlib

import msgpack
import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from teleop.control.codecs.base import RawFormat, unpack, unpack16
from teleop.control.codecs.deadband import _norm
from teleop.session import wire

floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
vectors = hnp.arrays(np.float64, st.integers(1, 70), elements=floats)
finite_vectors = hnp.arrays(np.float64, st.integers(1, 70), elements=st.floats(-1e150, 1e150))


@given(vectors, st.floats(0.01, 100.0))
def test_quantize_is_minimum_of_maximum(x: np.ndarray, full_scale: float) -> None:
    raw = RawFormat(full_scale)
    m = raw._max_code_f
    with np.errstate(invalid="ignore", over="ignore"):
        want = np.minimum(np.maximum(x * raw._inv_step, -m), m).astype(np.int64)
        got = raw.quantize(x)
    assert got.dtype == want.dtype and np.array_equal(got, want)


@given(st.binary(min_size=0, max_size=140).filter(lambda b: len(b) % 2 == 0), st.floats(0.01, 100.0))
def test_unpack16_dequantizes_as_unpack(data: bytes, full_scale: float) -> None:
    raw = RawFormat(full_scale)
    n = len(data) // 2
    a, b = raw.dequantize(unpack16(data, n)), raw.dequantize(unpack(data, 16, n))
    assert a.dtype == b.dtype == np.float64
    assert a.tobytes() == b.tobytes()


@given(finite_vectors)
def test_norm_is_numpys(x: np.ndarray) -> None:
    assert _norm(x) == float(np.linalg.norm(x)) or (math.isnan(_norm(x)) and math.isnan(np.linalg.norm(x)))


u32, u64 = st.integers(0, 2**32 - 1), st.integers(0, 2**64 - 1)


@given(u32, st.integers(0, 1), u32, u64, u64, st.integers(0, 255), st.binary(max_size=300), floats)
def test_encode_is_packb(
    session: int, direction: int, seq: int, tick: int, t_us: int, codec_id: int, payload: bytes, energy: float
) -> None:
    p = wire.Packet(session, direction, seq, tick, t_us, codec_id, payload, energy)
    fields = [wire.MAGIC, wire.VERSION, session, direction, seq, tick, t_us, codec_id, payload, float(energy)]
    body = msgpack.packb(fields, use_bin_type=True)
    assert wire.encode(p) == body + zlib.crc32(body).to_bytes(4, "little")


@given(st.floats(-1e6, 1e6))
def test_math_sin_cos_are_numpys_for_a_float(t: float) -> None:
    """``teleop.devices.models`` calls math.sin and math.cos on the 1 kHz path where it called np.sin and
    np.cos on a Python float: numpy's float64 loop calls the same libm, so the bits agree."""
    assert math.sin(t) == float(np.sin(t)) or (math.isnan(math.sin(t)) and math.isnan(float(np.sin(t))))
    assert math.cos(t) == float(np.cos(t)) or (math.isnan(math.cos(t)) and math.isnan(float(np.cos(t))))
