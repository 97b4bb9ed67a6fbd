"""The report's streamed I_dc and drift (teleop.control.metrics.DelayDistortionFold) equal their whole-array
definitions (delay_compensated, position_drift) for any split of the session into blocks."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop.control import metrics


@settings(max_examples=150)
@given(
    n=st.integers(1, 300),
    dof=st.integers(1, 3),
    sf=st.integers(0, 80),
    sb=st.integers(0, 80),
    cuts=st.lists(st.integers(1, 60), min_size=1, max_size=40),
    seed=st.integers(0, 2**32 - 1),
)
def test_the_fold_equals_the_whole_array_figures(
    n: int, dof: int, sf: int, sb: int, cuts: list[int], seed: int
) -> None:
    rng = np.random.default_rng(seed)
    vh, vt, fh, ft = (rng.normal(size=(n, dof)) for _ in range(4))
    fold = metrics.DelayDistortionFold(dof, 1e-3, sf, sb)
    i, c = 0, 0
    while i < n:
        m = cuts[c % len(cuts)]
        fold.add(vh[i : i + m], vt[i : i + m], fh[i : i + m], ft[i : i + m])
        i, c = i + m, c + 1
    want = metrics.delay_compensated(vh, vt, fh, ft, 1e-3, sf, sb)
    drift = metrics.position_drift(vh, vt, 1e-3, sf)
    assert np.isclose(fold.i_dc, want, rtol=1e-12, atol=1e-15)
    assert np.isclose(fold.drift()["max"], drift["max"], rtol=1e-9, atol=1e-15)
    assert np.isclose(fold.drift()["final"], drift["final"], rtol=1e-9, atol=1e-15)


def test_a_tick_one_process_did_not_run_is_left_out() -> None:
    """NaN rows (a late joiner's ticks before it ran) add nothing to I_dc and no motion."""
    v = np.ones((10, 1))
    vt = v.copy()
    vt[:4] = np.nan
    fold = metrics.DelayDistortionFold(1, 1e-3, 0, 0)
    fold.add(v, vt, np.zeros((10, 1)), np.zeros((10, 1)))
    assert fold.i_dc == 0.0
    assert np.isclose(fold.drift()["final"], 4e-3)  # the robot did not move while it did not run
