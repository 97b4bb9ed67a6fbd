"""``pdr``, the reflection-aware predictive deadband (``teleop.control.codecs.reflective``, issue 23 item 6).

Its two ends are paired per node: the backward receiver plays the reflection of the forward wave its
own sender modelled, so the properties are checked on a whole loop (operator and teleoperator, each
with its encoder and decoder paired as ``teleop.session.node`` pairs them) on arbitrary signals, lossless
and lossy; then in ``teleop sim`` on the protocol scenario under the watchdog's impairment matrix.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from teleop.control.codecs import CodecError, make_codec
from teleop.control.codecs.reflective import (
    REFLECTION_MIN_POWER,
    RESERVE_SCALE,
    Reflection,
    ReflectiveDecoder,
    ReflectiveEncoder,
)
from teleop.control.passivity import EnergyGuard
from teleop.offline.sim import SimConfig, run_case
from teleop.session import wire
from teleop.session.settings import Passivity
from tests.test_watchdog_matrix import IMPAIRMENTS
from tests.test_watchdog_matrix import run as run_matrix_case

DT = 1e-3
#: pdr's default frontier point (bench/frontier0.py's grid has it).
WINNER = "pdr:0.8"
#: The per-direction point (backward band 1 %, reserve scales 128 % forward and 86 % backward):
#: bench/frontier0.py's frontier, which it runs through the matrix on the full 15 s.
SPLIT = "pdr:0.8:100:1:128:86"

#: Two waves per tick (the operator's g_l, the teleoperator's h_r), DoF 1..3, beyond the range.
loops = st.integers(1, 3).flatmap(
    lambda dof: arrays(
        np.float64,
        st.tuples(st.integers(1, 300), st.just(2), st.just(dof)),
        elements=st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False),
    )
)


def _loop(
    spec: str, x: np.ndarray, keep: list[bool] | None = None
) -> tuple[tuple[EnergyGuard, EnergyGuard], list[float], bool]:
    """Both directions of one session, in ``teleop.offline.sim``'s order at zero delay: the operator plays
    the backward payload of the previous tick and sends; the teleoperator plays the forward payload
    of this tick and sends.  Returns the guards, the smallest true margins (J) and whether every
    decoder played exactly what its peer's sender modelled (before its guard)."""
    n, _, dof = x.shape
    op_c, to_c = make_codec(spec, dof=dof, full_scale=2.0), make_codec(spec, dof=dof, full_scale=2.0)
    op_enc, op_dec = op_c.encoder(), op_c.decoder(on_loss="hold")
    to_enc, to_dec = to_c.encoder(), to_c.decoder(on_loss="hold")
    assert isinstance(op_enc, ReflectiveEncoder) and isinstance(to_enc, ReflectiveEncoder)
    op_enc.pair(op_dec, wire.FORWARD)
    to_enc.pair(to_dec, wire.BACKWARD)
    g_op, g_to = EnergyGuard(DT), EnergyGuard(DT)
    sent = [0.0, 0.0]
    played = [0.0, 0.0]
    worst = [math.inf, math.inf]
    exact = True
    backward: tuple[bytes, float] | None = None  # the teleoperator's payload of the last tick
    to_model = np.zeros(dof)
    for i in range(n):
        k = keep is None or keep[i % len(keep)]
        if backward is not None:
            op_dec.push(backward[0])
            g_op.sent(backward[1])
        h = op_dec.next()
        exact &= bool(np.array_equal(h, to_model))  # what the teleoperator modelled last tick
        y = g_op.admit(h)
        played[1] += 0.5 * DT * float(np.dot(y, y))
        sent[0] += 0.5 * DT * float(np.dot(x[i, 0], x[i, 0]))
        fwd = op_enc.encode(x[i, 0])
        if fwd is not None and k:
            to_dec.push(fwd)
            g_to.sent(sent[0])
        g = to_dec.next()
        exact &= bool(np.array_equal(g, op_enc.model))
        y = g_to.admit(g)
        played[0] += 0.5 * DT * float(np.dot(y, y))
        sent[1] += 0.5 * DT * float(np.dot(x[i, 1], x[i, 1]))
        bwd = to_enc.encode(x[i, 1])
        to_model = to_enc.model.copy()
        backward = (bwd, sent[1]) if bwd is not None and k else None
        for d in (0, 1):
            worst[d] = min(worst[d], sent[d] - played[d])
    return (g_to, g_op), worst, exact


@settings(max_examples=80, deadline=None)
@given(x=loops, spec=st.sampled_from(["pdr:0.8", "pdr:0.8:1000", "pdr:5", "pdr:1:7", "pdr:20"]))
def test_lossless_loop_plays_what_the_senders_modelled_within_budget(x: np.ndarray, spec: str) -> None:
    guards, worst, exact = _loop(spec, x)
    assert exact  # each receiver's reference and reconstruction are its peer's model, bit for bit
    assert min(worst) >= -1e-12  # eq. (5) per direction, at every tick: passive
    for guard in guards:
        assert guard.report.violations == 0  # the senders keep the receivers within their budgets


@settings(max_examples=80, deadline=None)
@given(
    x=loops,
    spec=st.sampled_from(["pdr:0.8", "pdr:2:5"]),
    keep=st.lists(st.booleans(), min_size=1, max_size=9),
)
def test_lossy_loop_is_passive_behind_the_guards(x: np.ndarray, spec: str, keep: list[bool]) -> None:
    """Lost payloads put the two ends' references out of step: the guards keep it passive."""
    _, worst, _ = _loop(spec, x, keep)
    assert min(worst) >= -1e-12


@settings(max_examples=60, deadline=None)
@given(
    g=arrays(np.float64, (200, 2), elements=st.floats(-2.0, 2.0, allow_nan=False)),
    rho=st.floats(-1.0, 1.0),
)
def test_reflection_finds_a_constant_coefficient(g: np.ndarray, rho: float) -> None:
    refl = Reflection(2)
    fitted = np.zeros(2, dtype=bool)
    for row in g:
        refl.add(row, rho * row)
        # A DoF is fitted once its forgotten sum of g^2 (Reflection's own test) exceeds the minimum:
        # the plain sum can (200 rows of 1e-4: 2e-6 against a forgotten 1.0e-6).
        fitted |= refl._gg > REFLECTION_MIN_POWER
    assert np.allclose(refl.rho[fitted], rho, atol=1e-9)
    assert np.all(refl.rho[~fitted] == 1.0)  # never fitted: the start value
    assert np.all(np.abs(refl.rho) <= 1.0)


@pytest.mark.parametrize(
    "spec,msg",
    [
        ("pdr", "takes pdr:PCT"),
        ("pdr:0", "PCT must be in"),
        ("pdr:101", "PCT must be in"),
        ("pdr:x", "PCT must be a number"),
        ("pdr:1:0", "MAXMS must be in"),
        ("pdr:1:1.5", "MAXMS must be an integer"),
        ("pdr:1:100:3:1", "takes pdr:PCT"),
        ("pdr:1:100:1:2:3:4:5:6", "takes pdr:PCT"),
        ("pdr:1:100:0", "BPCT must be in"),
        ("pdr:1:100:x", "BPCT must be a number"),
        ("pdr:1:100:1:x:100", "FR must be a number"),
        ("pdr:1:100:1:100:1001", "BR must be in"),
        ("pdr:1:100:1:-1:100", "FR must be in"),
        ("pdr:1:0:1", "MAXMS must be in"),
    ],
)
def test_bad_specs_say_what_is_allowed(spec: str, msg: str) -> None:
    with pytest.raises(CodecError, match=msg):
        make_codec(spec)


def test_spec_is_canonical_and_reuses_pdps_payload() -> None:
    c = make_codec("PDR:0.80:100", dof=3)
    assert c.spec == "pdr:0.8" and c.codec_id == 7 and c.klass == "deadband" and c.event_based
    assert c.payload_bytes == make_codec("pdp:1", dof=3).payload_bytes == 12
    assert make_codec("pdr:0.8:1000").k == 1000  # MAXMS: the link supervision's payload interval
    assert make_codec("pdr:1", power=True).codec_id == wire.POWER_CODEC_BASE + 7
    dec = make_codec("pdr:1", dof=2).decoder()
    assert isinstance(dec, ReflectiveDecoder)
    for bad in (b"", b"\x00", bytes(100)):
        with pytest.raises(CodecError):
            dec.push(bad)
    assert dec.queued == 0


def test_per_direction_settings_are_canonical_and_set_by_pair() -> None:
    """BPCT, FR and BR (teleop.control.codecs.reflective): the shortest spec that means the same, and each
    encoder takes its direction's band and reserve scale when the node pairs it."""
    assert make_codec("pdr:0.8:100:0.8").spec == "pdr:0.8"
    assert make_codec("pdr:0.8:100:0.8:100:100").spec == "pdr:0.8"
    assert make_codec("pdr:0.8:1000:1").spec == "pdr:0.8:1000:1"
    assert make_codec("pdr:0.8:100:0.8:128:86").spec == "pdr:0.8:100:0.8:128:86"
    assert make_codec(SPLIT).k == 100 and make_codec(SPLIT).codec_id == 7
    c = make_codec(SPLIT, dof=2)
    for direction, k, scale in ((wire.FORWARD, 0.008, 1.28), (wire.BACKWARD, 0.01, 0.86)):
        enc = c.encoder()
        assert isinstance(enc, ReflectiveEncoder)
        enc.pair(c.decoder(), direction)
        assert enc.k == pytest.approx(k)
        assert enc.reserve_scale == pytest.approx(RESERVE_SCALE * scale)
    # The defaults leave pdr's schedule as it was, bit for bit.
    enc = make_codec("pdr:0.8:100:0.8:100:100").encoder()
    assert isinstance(enc, ReflectiveEncoder) and enc.reserve_scale == RESERVE_SCALE


@settings(max_examples=60, deadline=None)
@given(
    x=loops,
    spec=st.sampled_from([SPLIT, "pdr:1:7:3:400:0", "pdr:5:100:0.5:0:300"]),
    keep=st.one_of(st.none(), st.lists(st.booleans(), min_size=1, max_size=9)),
)
def test_split_loop_is_passive_and_in_step(x: np.ndarray, spec: str, keep: list[bool] | None) -> None:
    """The per-direction settings change only when each side sends and how much it shrinks: the
    loop stays passive, lossless or lossy, and lossless each receiver plays what its sender
    modelled within its budget."""
    guards, worst, exact = _loop(spec, x, keep)
    assert min(worst) >= -1e-12
    if keep is None:
        assert exact
        for guard in guards:
            assert guard.report.violations == 0


@pytest.mark.parametrize("passivity", ["wave", "tdpa"])
def test_winner_in_the_sim_beats_pdp_on_packets_and_stays_passive(passivity: Passivity) -> None:
    """The frontier point, measured short: fewer packets than pdp:1 each way at zero delay."""
    s = run_case(SimConfig(codec=WINNER, scenario="protocol", duration=6.0, passivity=passivity)).summary
    assert s["passive"] and s["min_energy_margin"] >= -1e-9 and s["two_port_min_energy"] >= -1e-9
    if passivity == "wave":
        ref = run_case(SimConfig(codec="pdp:1", scenario="protocol", duration=6.0)).summary
        for d in ("forward", "backward"):
            assert s["wire"][d]["packets"] < ref["wire"][d]["packets"], d
            assert s["passivity"][d]["violations"] == 0, d  # lossless: the guards never cut
        assert s["I"] < 1.5 * ref["I"]


@pytest.mark.parametrize("codec", [WINNER, SPLIT])
@pytest.mark.parametrize("name,imp", IMPAIRMENTS, ids=[n for n, _ in IMPAIRMENTS])
def test_winner_is_passive_under_the_watchdog_matrix(name: str, imp: dict[str, object], codec: str) -> None:
    """test_watchdog_matrix's matrix and assertions, for the frontier codecs: with "hold" only, as
    for the deadbands there, since pdr's decoder never reads ``on_loss``
    (test_watchdog_matrix.test_a_deadbands_reconstruction_ignores_on_loss)."""
    s = run_matrix_case(codec, imp, on_loss="hold", controller=True)
    assert s["min_energy_margin"] >= -1e-9, (s["energy"], s["passivity"])
    assert s["two_port_min_energy"] >= -1e-9
    assert s["passive"]
    for d in ("forward", "backward"):
        pv = s["passivity"][d]
        assert pv["min_margin"] >= -1e-9
        assert pv["controller_active_ticks"] == pv["violations"]
    assert np.isfinite(s["max_abs"]) and s["max_abs"] < 50.0
