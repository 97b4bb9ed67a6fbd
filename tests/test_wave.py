"""Scattering transform (eq. 3), its inverse, and the energy identities (2)-(4)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from teleop.control.wave import WaveError, WaveImpedance, power

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


@st.composite
def port(draw: st.DrawFn) -> tuple[WaveImpedance, np.ndarray, np.ndarray]:
    dof = draw(st.integers(1, 6))
    b = draw(hnp.arrays(np.float64, dof, elements=st.floats(1e-3, 1e3)))
    v = draw(hnp.arrays(np.float64, dof, elements=finite))
    f = draw(hnp.arrays(np.float64, dof, elements=finite))
    return WaveImpedance.of(b, dof), v, f


@given(port())
def test_round_trip(p: tuple[WaveImpedance, np.ndarray, np.ndarray]) -> None:
    w, v, f = p
    g, h = w.to_waves(v, f)
    v2, f2 = w.from_waves(g, h)
    np.testing.assert_allclose(v2, v, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(f2, f, rtol=1e-9, atol=1e-9)


@given(port())
def test_power_identity(p: tuple[WaveImpedance, np.ndarray, np.ndarray]) -> None:
    """v . F = (g.g - h.h) / 2, the per-port identity behind eq. (4)."""
    w, v, f = p
    g, h = w.to_waves(v, f)
    assert power(g, h) == pytest.approx(float(np.dot(v, f)), rel=1e-9, abs=1e-6)


@given(port(), st.data())
def test_mixed_forms_agree_with_eq3(
    p: tuple[WaveImpedance, np.ndarray, np.ndarray], data: st.DataObject
) -> None:
    w, v, f = p
    g, h = w.to_waves(v, f)
    # HSI: knows v and receives h; TO: receives g and knows F.
    np.testing.assert_allclose(w.hsi_force(v, h), f, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(w.hsi_wave_out(v, h), g, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(w.to_velocity(g, f), v, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(w.to_wave_out(g, f), h, rtol=1e-9, atol=1e-6)


@given(st.integers(1, 4), st.integers(1, 200), st.data())
def test_energy_balance_eq4(dof: int, n: int, data: st.DataObject) -> None:
    """sum(P_in) dt = 1/2 sum(g_l^2 - g_r^2 + h_r^2 - h_l^2) dt for arbitrary port signals (eq. 2-4)."""
    w = WaveImpedance.of(data.draw(st.floats(0.01, 100)), dof)
    sig = hnp.arrays(np.float64, (n, dof), elements=st.floats(-100, 100))
    v_h, f_h, v_t, f_t = (data.draw(sig) for _ in range(4))
    dt = 1e-3
    p_in = float(np.sum(v_h * f_h - v_t * f_t)) * dt
    rhs = 0.0
    for k in range(n):
        gl, hl = w.to_waves(v_h[k], f_h[k])
        gr, hr = w.to_waves(v_t[k], f_t[k])
        rhs += 0.5 * float(gl @ gl - gr @ gr + hr @ hr - hl @ hl) * dt
    assert rhs == pytest.approx(p_in, rel=1e-9, abs=1e-6)


@pytest.mark.parametrize("b", [0.0, -1.0, float("nan"), float("inf"), [1.0, 0.0]])
def test_bad_impedance(b: object) -> None:
    with pytest.raises(WaveError, match="b must be finite and > 0"):
        WaveImpedance.of(b, 2)  # type: ignore[arg-type]


def test_bad_shapes() -> None:
    with pytest.raises(WaveError, match=r"shape \(3,\)"):
        WaveImpedance.of([1.0, 2.0], 3)
    with pytest.raises(WaveError, match="positive integer"):
        WaveImpedance.of(1.0, 0)
    w = WaveImpedance.of(1.0, 2)
    with pytest.raises(WaveError, match="does not match dof 2"):
        w.to_waves(np.zeros(3), np.zeros(3))
    with pytest.raises(WaveError, match="does not match dof 2"):
        w.from_waves(np.zeros(2), np.zeros(1))


def test_per_dof_impedance() -> None:
    w = WaveImpedance.of([1.0, 4.0], 2)
    g, h = w.to_waves(np.array([1.0, 1.0]), np.array([0.0, 0.0]))
    np.testing.assert_allclose(g, [1 / np.sqrt(2), 4 / np.sqrt(8)])
    np.testing.assert_allclose(h, g)
