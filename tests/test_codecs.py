"""Every codec's reconstruction satisfies its passivity condition on arbitrary signals.

Signals are drawn by hypothesis: any amplitude (inside and beyond the full scale), either sign,
zero crossings, constant runs, any length and DoF.  The channel is lossless and in order, as the
paper assumes; delay does not change what is played, only when.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from teleop.control.codecs import Codec, CodecError, make_codec
from teleop.control.codecs.base import RawFormat, pack, packed_size, unpack

TOL = 1e-12


def run(codec: Codec, x: np.ndarray) -> tuple[np.ndarray, int]:
    """Encode every tick, deliver in the same tick, play one sample per tick."""
    enc, dec = codec.encoder(), codec.decoder()
    y = np.empty_like(x)
    sent = 0
    for n in range(x.shape[0]):
        p = enc.encode(x[n])
        if p is not None:
            assert len(p) == codec.payload_bytes
            sent += 1
            dec.push(p)
        y[n] = dec.next()
    return y, sent


@st.composite
def signal(draw: st.DrawFn, max_len: int = 300) -> np.ndarray:
    n = draw(st.integers(1, max_len))
    dof = draw(st.integers(1, 4))
    elems = st.one_of(st.floats(-40, 40), st.sampled_from([0.0, 1e-9, -1e-9, 2.0, -2.0, 100.0, -100.0]))
    return draw(hnp.arrays(np.float64, (n, dof), elements=elems))


full_scales = st.sampled_from([0.5, 2.0, 16.0, 100.0])


def cumulative_margin(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per DoF: sum_{m<=n} (x^2 - y^2), the discrete form of eq. (5)."""
    return np.cumsum(x * x - y * y, axis=0)


@settings(max_examples=150, deadline=None)
@given(signal(), st.integers(2, 16), full_scales)
def test_cq_eq11_every_sample(x: np.ndarray, bits: int, fs: float) -> None:
    codec = make_codec(f"cq:{bits}", x.shape[1], fs)
    y, sent = run(codec, x)
    assert sent == x.shape[0]
    assert np.all(np.abs(y) <= np.abs(x) + TOL)  # eq. (11)
    assert np.all(y * x >= 0)  # rounding toward zero never flips a sign
    step = fs / ((1 << (bits - 1)) - 1)
    inside = np.abs(x) <= fs
    assert np.all(np.abs(x - y)[inside] < step * (1 + 1e-9))  # and it loses less than one step


@settings(max_examples=150, deadline=None)
@given(signal(), full_scales)
def test_none_is_raw_16_bit(x: np.ndarray, fs: float) -> None:
    codec = make_codec("none", x.shape[1], fs)
    y, sent = run(codec, x)
    assert sent == x.shape[0]
    assert np.all(np.abs(y) <= np.abs(x) + TOL)
    inside = np.abs(x) <= fs
    assert np.all(np.abs(x - y)[inside] < fs / 32767 * (1 + 1e-9))


@settings(max_examples=150, deadline=None)
@given(signal(), st.integers(1, 60), full_scales)
def test_ids_eq8_every_frame(x: np.ndarray, k: int, fs: float) -> None:
    codec = make_codec(f"ids:{k}", x.shape[1], fs)
    y, sent = run(codec, x)
    n = x.shape[0]
    assert sent == n // k
    # One frame of delay: nothing is played before the first frame is complete.
    assert np.all(y[: k - 1] == 0)
    for j in range(n // k):
        frame_in = x[j * k : (j + 1) * k]
        frame_out = y[j * k + k - 1 : j * k + 2 * k - 1]  # played from the tick the frame completes
        e_in = np.sum(frame_in**2, axis=0)
        e_out = np.sum(frame_out**2, axis=0)
        assert np.all(e_out <= e_in + TOL * (1 + e_in))  # eq. (8), per DoF
    assert np.all(cumulative_margin(x, y) >= -TOL * (1 + np.cumsum(x * x, axis=0)))


@settings(max_examples=150, deadline=None)
@given(signal(), st.integers(1, 60), full_scales)
def test_eds_eq10_budget(x: np.ndarray, k: int, fs: float) -> None:
    codec = make_codec(f"eds:{k}", x.shape[1], fs)
    y, sent = run(codec, x)
    n = x.shape[0]
    assert sent == -(-n // k)
    # Sample-based: no delay; each value is held for exactly K ticks.
    for j in range(sent):
        block = y[j * k : min((j + 1) * k, n)]
        assert np.all(block == block[0])
    # Eq. (10) at every horizon start t_j: energy in so far minus played before t_j covers the horizon.
    e_in = np.cumsum(x * x, axis=0)
    played_before = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(y * y, axis=0)])
    for j in range(sent):
        t = j * k
        horizon = k * y[t] ** 2
        assert np.all(e_in[t] - played_before[t] >= horizon - TOL * (1 + e_in[t]))
    assert np.all(cumulative_margin(x, y) >= -TOL * (1 + e_in))


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 50))
def test_eds_holds_latest_value_when_budget_allows(k: int) -> None:
    """With energy to spare, eDS sends the most recent sample, as Section V.B says."""
    codec = make_codec(f"eds:{k}", 1, 2.0)
    x = np.concatenate([np.full((5 * k, 1), 1.0), np.full((3 * k, 1), 0.25)])
    y, _ = run(codec, x)
    raw = RawFormat(2.0)
    np.testing.assert_array_equal(y[-k:], raw.dequantize(raw.quantize(np.array([0.25])))[0])


@pytest.mark.parametrize(
    "spec,c",
    [
        ("none", 1),
        ("ids:2", 2),
        ("ids:50", 50),
        ("eds:2", 2),
        ("eds:50", 50),
        ("cq:8", 2),
        ("cq:4", 4),
        ("cq:16", 1),
    ],
)
def test_nominal_compression(spec: str, c: float) -> None:
    assert make_codec(spec, 2).nominal_compression == c


@pytest.mark.parametrize("bits", range(2, 17))
@pytest.mark.parametrize("dof", [1, 2, 3, 6])
def test_pack_round_trip_and_truncation(bits: int, dof: int) -> None:
    rng = np.random.default_rng(bits * 10 + dof)
    m = (1 << (bits - 1)) - 1
    q = rng.integers(-m, m + 1, dof)
    data = pack(q, bits)
    assert len(data) == packed_size(dof, bits)
    np.testing.assert_array_equal(unpack(data, bits, dof), q)
    for cut in range(len(data)):
        with pytest.raises(CodecError, match="payload has"):
            unpack(data[:cut], bits, dof)
    with pytest.raises(CodecError, match="payload has"):
        unpack(data + b"\0", bits, dof)


def test_padding_bits_rejected() -> None:
    with pytest.raises(CodecError, match="padding"):
        unpack(b"\xff", 5, 1)


@pytest.mark.parametrize(
    "spec,msg",
    [
        ("", "empty codec spec"),
        ("zip", "unknown codec 'zip'"),
        ("ids", "takes ids:K, got 0"),
        ("ids:x", "K must be an integer, got 'x'"),
        ("eds:0", "K must be in 1..100000, got 0"),
        ("cq:1", "BITS must be in 2..16, got 1"),
        ("cq:17", "BITS must be in 2..16, got 17"),
        ("cq:8:-1", "full scale"),
        ("cq:8:abc", "RANGE must be a number"),
        ("none:3", "takes no parameter"),
    ],
)
def test_bad_specs_list_what_is_accepted(spec: str, msg: str) -> None:
    with pytest.raises(CodecError, match=msg) as e:
        make_codec(spec)
    if spec.startswith(("zip", "ids", "eds:", "cq:1", "cq:17")):
        assert "accepted: none | ids:K | eds:K | cq:BITS" in str(e.value)


def test_decoder_zero_fills_and_bounds_queue() -> None:
    codec = make_codec("eds:3", 1, 2.0)
    enc, dec = codec.encoder(), codec.decoder(max_queue=4)
    assert dec.next()[0] == 0.0 and dec.underruns == 1
    p = enc.encode(np.array([1.0]))
    assert p is not None
    dec.push(p)
    dec.push(p)  # 6 ticks queued > 4: the oldest 2 are dropped, never more played than sent
    assert dec.queued == 4 and dec.dropped_samples == 2
    with pytest.raises(CodecError):
        dec.push(b"\x00")
    assert dec.queued == 4
