"""Issue 46: the export's fast paths give exactly what the careful ones give.

``teleop export`` reads a 10 s session in under 1/50 of its length by taking shortcuts: the robot's
state parsed by pyarrow (falling back to a sample-by-sample walk that names every fault), LeRobot's
statistics from one sort (where numpy's nan* reductions were used), Arrow arrays over numpy's
buffers, a log's summary found through the chunks' message indexes.  Each is held here to the
path it replaced, on random and hostile input, bit for bit where the old path was exact.
"""

from __future__ import annotations

import json
import math
import warnings
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop.offline import lerobot
from teleop.offline.logfile import LogError, _states_arrow, _states_python

TOPIC = "/teleoperator/state"
FINITE = st.floats(allow_nan=False, allow_infinity=False, width=64)


def _walk(blocks: list[bytes], max_tick: int) -> Any:
    """The careful path's answer: its result, or the fault it names."""
    try:
        return _states_python(blocks, TOPIC, max_tick)
    except LogError as e:
        return e


def _same(a: Any, b: Any) -> bool:
    ka, na, va = a
    kb, nb, vb = b
    return (
        na == nb
        and ka.dtype == kb.dtype == np.int64
        and np.array_equal(ka, kb)
        and va.dtype == vb.dtype == np.float64
        and va.shape == vb.shape
        and np.array_equal(va.view(np.uint64), vb.view(np.uint64))  # NaN's bits too
    )


def _lines(samples: list[dict[str, Any]], per_block: int) -> list[bytes]:
    """Samples as topic_lines hands them: blocks of newline-separated JSON, blank-padded."""
    text = [json.dumps(m).encode() + b" " * 30 for m in samples]
    return [b"\n" + b"\n".join(text[i : i + per_block]) + b"\n" for i in range(0, len(text), per_block)]


@st.composite
def _states(draw: st.DrawFn) -> tuple[list[bytes], int]:
    """A device's state samples as a log holds them: mostly well formed, some of them not."""
    layout = draw(st.lists(st.tuples(st.sampled_from(["pose", "q", "dq", "tau", "w", "x.y"]),
                                     st.integers(-1, 4)), max_size=4, unique_by=lambda f: f[0]))  # fmt: skip
    n = draw(st.integers(0, 30))
    ks = sorted(draw(st.lists(st.integers(0, 200), min_size=n, max_size=n, unique=True)))
    values = st.one_of(FINITE, st.just(math.nan), st.integers(-(2**60), 2**60))
    samples: list[dict[str, Any]] = []
    for k in ks:
        m: dict[str, Any] = {"k": k, "t": k * 1e-3}
        for name, w in layout:
            m[name] = draw(values) if w < 0 else [draw(values) for _ in range(w)]
        samples.append(m)
    fault = draw(st.sampled_from(["none"] * 4 + ["k float", "k missing", "k bool", "field missing",
                                  "field extra", "width", "string", "bool", "null", "reorder",
                                  "order", "huge", "nested", "t string", "duplicate key"]))  # fmt: skip
    if samples and fault != "none":
        i = draw(st.integers(0, len(samples) - 1))
        m = samples[i]
        named = [n for n, _ in layout]
        if fault == "k float":
            m["k"] = float(m["k"])
        elif fault == "k missing":
            del m["k"]
        elif fault == "k bool":
            m["k"] = True
        elif fault == "field missing" and named:
            del m[named[0]]
        elif fault == "field extra":
            m["extra"] = 1.0
        elif fault == "width" and layout and layout[0][1] >= 0:
            m[named[0]] = [*m[named[0]], 1.0]
        elif fault in ("string", "bool", "null", "huge", "nested") and named:
            bad = {"string": "1", "bool": True, "null": None, "huge": 1e300, "nested": [1.0]}[fault]
            v = m[named[-1]]
            m[named[-1]] = [*v[:-1], bad] if isinstance(v, list) and v else bad
        elif fault == "reorder":
            samples[i] = dict(reversed(list(m.items())))
        elif fault == "order" and len(samples) > 1:
            samples[i], samples[-1] = samples[-1], samples[i]
        elif fault == "t string":
            m["t"] = "soon"
    blocks = _lines(samples, draw(st.integers(1, 8)))
    if fault == "duplicate key" and blocks:
        blocks[0] = blocks[0].replace(b'{"k": ', b'{"k": 0, "k": ', 1)
    return blocks, draw(st.sampled_from([10**6, 150]))


@settings(max_examples=400, deadline=None)
@given(_states())
def test_pyarrows_state_parse_is_the_walks_or_leaves_it_the_walk(case: tuple[list[bytes], int]) -> None:
    """Where the pyarrow parse answers, its ticks, names and values are the walk's, bit for bit;
    where the walk refuses a log, the parse does not answer (it returns None, and the walk's fault
    is what the user reads)."""
    blocks, max_tick = case
    walked = _walk(blocks, max_tick)
    fast = _states_arrow(blocks, max_tick)
    if isinstance(walked, LogError):
        assert fast is None, walked
    elif fast is not None:
        assert _same(fast, walked)


def test_pyarrows_state_parse_answers_a_well_formed_log() -> None:
    """The fast path is taken where it should be (a Franka's state: lists of numbers, and a scalar)."""
    samples = [{"k": k, "t": k / 1e3, "pose": [0.5, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0], "q": [0.1 * k] * 7,
                "gripper": 0.04} for k in range(0, 1000, 10)]  # fmt: skip
    blocks = _lines(samples, 37)
    fast = _states_arrow(blocks, 1000)
    assert fast is not None
    assert _same(fast, _states_python(blocks, TOPIC, 1000))
    assert fast[1][:2] == ["pose.0", "pose.1"] and fast[1][-1] == "gripper"


def test_a_sample_with_its_fields_in_another_order_is_the_same_sample() -> None:
    """A JSON object's key order carries no meaning: a sample written in another order reads as the
    first's layout (both paths), not as other fields."""
    a = {"k": 0, "t": 0.0, "q": [1.0, 2.0], "w": 3.0}
    b = {"w": 6.0, "q": [4.0, 5.0], "t": 0.01, "k": 10}
    ks, names, values = _states_python(_lines([a, b], 1), TOPIC, 100)
    assert names == ["q.0", "q.1", "w"] and values.tolist() == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    fast = _states_arrow(_lines([a, b], 1), 100)
    assert fast is not None and _same(fast, (ks, names, values))


def _numpys_stats(x: np.ndarray) -> dict[str, np.ndarray]:
    """The statistics as numpy's nan* reductions give them (the export's earlier code)."""
    v = x.astype(np.float64)
    v = v.reshape(-1, 1) if v.ndim == 1 else v.reshape(-1, v.shape[-1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out = {"min": np.nanmin(v, axis=0), "max": np.nanmax(v, axis=0), "mean": np.nanmean(v, axis=0),
               "std": np.nanstd(v, axis=0)}  # fmt: skip
        qs = np.nanquantile(v, lerobot.QUANTILES, axis=0)
    for i, q in enumerate(lerobot.QUANTILES):
        out[f"q{round(q * 100):02d}"] = qs[i]
    return out


@st.composite
def _feature(draw: st.DrawFn) -> np.ndarray:
    shape = draw(st.sampled_from([(1,), (7,), (3, 20), (5, 20, 3), (4, 2, 31), (2, 1, 1)]))
    scale = 10.0 ** draw(st.integers(-6, 6))
    x = np.random.default_rng(draw(st.integers(0, 2**32 - 1))).standard_normal(shape) * scale
    gaps = draw(st.sampled_from(["none", "some", "a column", "all"]))
    if gaps == "some":
        x[np.random.default_rng(len(shape)).random(shape) < 0.3] = math.nan
    elif gaps == "a column":
        x[..., 0] = math.nan
    elif gaps == "all":
        x[:] = math.nan
    if draw(st.booleans()):
        x = np.round(x)  # ties: quantiles between equal values
    return x.astype(draw(st.sampled_from([np.float64, np.float32])))


@settings(max_examples=300, deadline=None)
@given(_feature())
def test_one_sorts_statistics_are_numpys(x: np.ndarray) -> None:
    """min, max and every quantile exactly numpy's (its linear method, NaN left out); mean and
    std equal within float rounding (summed in another order); null where an element has no value."""
    got, want = lerobot._stats(x), _numpys_stats(x)
    assert got["count"].tolist() == [x.shape[0]]
    for key, w in want.items():
        g = got[key]
        assert g.shape == w.shape, key
        if key in ("mean", "std"):
            np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-300, equal_nan=True, err_msg=key)
        else:
            assert np.array_equal(g, w, equal_nan=True), key  # exactly equal, not within rounding


def test_an_arrow_array_over_a_numpy_buffer_is_pyarrows_own() -> None:
    """``_flat_array`` gives what ``pa.array`` gives for every dtype the export writes, and refuses
    a bool (Arrow packs booleans in bits, numpy in bytes)."""
    import pyarrow as pa

    for dtype in (np.float64, np.float32, np.int64, np.int32, np.int8, np.uint8):
        x = (np.arange(24).reshape(2, 3, 4) - 5).astype(dtype)
        assert lerobot._flat_array(x).equals(pa.array(x.reshape(-1)))
    with pytest.raises(TypeError, match="not a numeric array"):
        lerobot._flat_array(np.array([True, False]))
