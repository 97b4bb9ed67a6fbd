"""Tustin-discretised models: accuracy against the analytic responses, and passivity."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from teleop.devices.models import (
    FLOAT_LANES,
    DiscreteLTI,
    LtiEnvironment,
    ModelError,
    ProtocolEnvironment,
    ProtocolHuman,
    ProtocolPlan,
    StepHuman,
    _smooth_steps,
)

DT = 1e-3


def step_response(num: tuple[float, ...], den: tuple[float, ...], n: int) -> np.ndarray:
    lti = DiscreteLTI(num, den, DT, 1)
    return np.array([lti.advance(np.ones(1))[0] for _ in range(n)])


def test_environment_step_matches_analytic() -> None:
    """1/(s+1): y = 1 - exp(-t); Tustin's trapezoid error is O(dt^2)."""
    y = step_response((1.0,), (1.0, 1.0), 3001)
    t = np.arange(3001) * DT
    np.testing.assert_allclose(y[1:], 1 - np.exp(-t[1:]), atol=1e-3)  # first sample: half-step of Tustin
    assert abs(y[1000] - (1 - np.exp(-1.0))) < 1e-3


def test_human_admittance_step_matches_analytic() -> None:
    """s/(s+0.5): y = exp(-t/2)."""
    y = step_response((1.0, 0.0), (1.0, 0.5), 3001)
    t = np.arange(3001) * DT
    np.testing.assert_allclose(y[10:], np.exp(-0.5 * t[10:]), atol=1e-3)


def test_second_order_is_supported() -> None:
    """A mass-spring-damper admittance s/(m s^2 + d s + k) settles to zero velocity under a step force."""
    y = step_response((1.0, 0.0), (1.0, 2.0, 100.0), 20000)
    assert abs(y[-1]) < 1e-6 and np.max(np.abs(y)) > 0.01


@settings(max_examples=60, deadline=None)
@given(
    hnp.arrays(np.float64, st.integers(1, 400), elements=st.floats(-10, 10)),
    st.sampled_from([((1.0,), (1.0, 1.0)), ((1.0, 0.0), (1.0, 0.5)), ((2.0, 3.0), (1.0, 0.1))]),
)
def test_discrete_models_are_passive(u: np.ndarray, tf: tuple[tuple[float, ...], tuple[float, ...]]) -> None:
    """Tustin keeps positive-real models passive: sum(u y) >= 0 from rest, for any input (eq. 1)."""
    lti = DiscreteLTI(tf[0], tf[1], DT, 1)
    acc = 0.0
    for x in u:
        y = lti.advance(np.array([x]))[0]
        acc += x * y
        assert acc >= -1e-9 * (1 + abs(acc))


def test_affine_matches_advance() -> None:
    """affine() predicts exactly what advance() will output for the settled input."""
    env = LtiEnvironment(2, DT)
    rng = np.random.default_rng(0)
    for _ in range(50):
        v = rng.normal(size=2)
        f0, z = env.affine(0.0)
        predicted = f0 + z * v
        out = env.impedance.advance(v)
        np.testing.assert_allclose(out, predicted, rtol=1e-12)


def test_step_human_reference() -> None:
    h = StepHuman(1, DT, amplitude=2.0, t_step=0.1)
    assert h.reference(0.099)[0] == 0.0 and h.reference(0.0995)[0] == 2.0 and h.reference(3.0)[0] == 2.0


@pytest.mark.parametrize("num,den", [((1.0, 0.0, 0.0), (1.0, 1.0)), ((1.0,), (0.0,)), ((1.0,), ())])
def test_improper_rejected(num: tuple[float, ...], den: tuple[float, ...]) -> None:
    with pytest.raises(ModelError, match="proper"):
        DiscreteLTI(num, den, DT, 1)


# --- the float lanes (issue 22): the same bits as the numpy path -------------------------------
TFS = [
    ((2.5,), (1.0,)),  # order 0: a pure gain
    ((1.0,), (1.0, 1.0)),
    ((1.0, 0.0), (1.0, 0.5)),
    ((1.0, 0.0), (1.0, 2.0, 100.0)),
    ((1.0, 2020.0, 0.0), (20.0, 2400.0, 46000.0, 600000.0)),  # the protocol human's third order
]


@settings(max_examples=80, deadline=None)
@given(
    hnp.arrays(np.float64, st.tuples(st.integers(1, 60), st.integers(1, 8)), elements=st.floats(-1e6, 1e6)),
    st.sampled_from(TFS),
)
def test_lanes_give_the_numpy_paths_bits(
    u: np.ndarray, tf: tuple[tuple[float, ...], tuple[float, ...]]
) -> None:
    """DiscreteLTI on floats, channel by channel, is the numpy recursion to the bit: output, free
    response and state, on any input, at every order (the sim goldens cover the models' own inputs)."""
    ch = u.shape[1]
    fl, ar = DiscreteLTI(*tf, DT, ch, lanes=True), DiscreteLTI(*tf, DT, ch, lanes=False)
    for row in u:
        assert fl.free().tobytes() == ar.free().tobytes()
        assert fl.advance(row).tobytes() == ar.advance(row).tobytes()
    fl.commit(u[0])
    ar.commit(u[0])
    assert fl.free_lanes() == ar.free().tolist()


def test_lanes_by_channel_count() -> None:
    """Floats up to FLOAT_LANES channels, numpy above (where one call per row is cheaper)."""
    assert DiscreteLTI((1.0,), (1.0, 1.0), DT, FLOAT_LANES).lanes
    assert not DiscreteLTI((1.0,), (1.0, 1.0), DT, FLOAT_LANES + 1).lanes


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 7), st.lists(st.floats(0.0, 400.0), min_size=1, max_size=50))
def test_protocol_reference_lanes_are_reference(dof: int, times: list[float]) -> None:
    """math.sin per lateral DoF gives np.sin's bits (the lanes' reference against the numpy one)."""
    h = ProtocolHuman(dof, DT, plan=ProtocolPlan.draw(3, 1.0))
    for t in times:
        assert h.reference_lanes(t) == h.reference(t).tolist()


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**16), st.lists(st.floats(0.0, 30.0), min_size=1, max_size=80))
def test_smooth_steps_resumed_is_from_the_start(seed: int, times: list[float]) -> None:
    """The push profile resumed from the last settled knot is the profile from the first knot, bit
    for bit, for times in any order (a time before the last one starts from the first knot again)."""
    h = ProtocolHuman(1, DT, plan=ProtocolPlan.draw(seed, 1.0))
    knots = h.plan.knots()
    for t in sorted(times) + times:
        if t >= h.plan.t_foam:  # before it, the free-space strokes
            assert h.push_profile(t) == _smooth_steps(t, knots, 0.15)[0]


def test_protocol_environment_out_of_contact_is_constant() -> None:
    """Out of contact the environment's map is the same read-only arrays every tick (so the node
    derives ``b + Z`` once per phase); in contact it is fresh arrays, and the shared ones unchanged."""
    env = ProtocolEnvironment(2, DT)
    a, b = env.affine(1.0), env.affine(1.001)
    assert a[0] is b[0] and a[1] is b[1] and not a[1].flags.writeable
    foam = env.affine(6.0)
    assert foam[1].tolist() == [env.foam, env.foam] and foam[1] is env.affine(6.001)[1]
    env.affine(10.0)  # places the wall gap ahead of x
    assert env.wall is not None
    env.x[0] = env.wall + 0.01  # pressed in
    f0, z = env.affine(10.001)
    assert f0[0] == env.k * (env.x[0] - env.wall) and z[0] == env.foam + (env.k * DT + env.c)
    assert z is not foam[1] and foam[1].tolist() == [env.foam, env.foam]
