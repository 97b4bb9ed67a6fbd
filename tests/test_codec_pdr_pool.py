"""``pdr``'s two-port accounting (``teleop.control.codecs.reflective``): cKAPPA self-credit.

A side credits its guard with energy it sent and has not reported, and withholds it from its reports
(``EnergyGuard.credit``).  Per-direction margins (eq. 5) may then go negative by design; the
channel's condition is eq. (1) with (4), the two-port's energy, checked here at every tick on
arbitrary signals, delays and losses, with both guards' in-band margins never negative.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop.control.codecs import CodecError, make_codec
from teleop.control.codecs.reflective import ReflectiveEncoder
from teleop.control.passivity import EnergyGuard
from teleop.offline.sim import SimConfig, run_case
from teleop.session import wire
from tests.ran import RAN
from tests.test_codec_pdr import loops  # two waves per tick, DoF 1..3, beyond the range

DT = 1e-3
#: The self-credit point bench/frontier0.py --pool measures: bands 0.8 %, reserve scales 30 %, kappa 1 %.
CREDIT = "pdr:0.8:100:0.8:30:30:c1"


def _two_port_loop(
    spec: str, x: np.ndarray, delay: int, keep: list[bool] | None
) -> tuple[float, float, bool]:
    """Both directions as ``teleop.offline.sim`` runs them, each payload ``delay`` extra ticks late and
    lost where ``keep`` says so; each report carries energy sent less withheld, as the node's.
    Returns the smallest two-port energy (J), the smallest guard margin (J) and whether anything
    was self-credited."""
    n, _, dof = x.shape
    c = make_codec(spec, dof=dof, full_scale=2.0)
    encs: list[ReflectiveEncoder] = []
    for _ in range(2):
        enc = c.encoder()
        assert isinstance(enc, ReflectiveEncoder)
        encs.append(enc)
    decs = [c.decoder(on_loss="hold"), c.decoder(on_loss="hold")]
    guards = [EnergyGuard(DT), EnergyGuard(DT)]  # [0] at the operator (plays h), [1] at the teleoperator
    for side, direction in ((0, wire.FORWARD), (1, wire.BACKWARD)):
        encs[side].pair(decs[side], direction, guards[side])
    sent = [0.0, 0.0]  # J: forward (operator), backward (teleoperator)
    links: list[deque[tuple[int, int, bytes, float]]] = [deque(), deque()]
    rx_tick = [0, 0]
    two_port = guard_min = np.inf
    for i in range(n):
        for side in (0, 1):
            # The operator hears the backward link from the previous tick, the teleoperator the forward
            # link from this one (the sim's one-tick loop floor), ``delay`` ticks later still.
            link = links[1 - side]
            while link and link[0][0] <= i:
                _, rx_tick[side], payload, energy = link.popleft()
                decs[side].push(payload)
                guards[side].sent(energy)
            guards[side].admit(decs[side].next())
            if getattr(decs[side], "fresh", False) and encs[side].rx_lag is not None:
                encs[side].rx_lag = i - rx_tick[side]  # as teleop.session.node tells it
            sent[side] += 0.5 * DT * float(np.dot(x[i, side], x[i, side]))
            out = encs[side].encode(x[i, side])
            lost = keep is not None and not keep[i % len(keep)]
            if out is not None and not lost:
                links[side].append((i + delay + side, i, out, sent[side] - encs[side].withheld))
            two_port = min(two_port, sent[0] + sent[1] - guards[0].played - guards[1].played)
            guard_min = min(guard_min, guards[0].margin, guards[1].margin)
    return float(two_port), float(guard_min), encs[0].withheld != 0.0 or encs[1].withheld != 0.0


@settings(max_examples=80, deadline=None)
@given(
    x=loops,
    spec=st.sampled_from(
        [
            CREDIT,
            "pdr:2:100:5:0:0:c0",
            "pdr:0.5:10:0.5:100:100:c5",
        ]
    ),
    delay=st.integers(0, 40),
    keep=st.one_of(st.none(), st.lists(st.booleans(), min_size=1, max_size=9)),
)
def test_two_port_energy_never_negative(
    x: np.ndarray, spec: str, delay: int, keep: list[bool] | None
) -> None:
    """Eq. (5) over both directions at every tick, whatever the signal, delay or losses; each
    guard's in-band margin (credits added) never negative either."""
    two_port, guard_min, _ = _two_port_loop(spec, x, delay, keep)
    assert two_port >= -1e-12
    assert guard_min >= -1e-12


def test_credit_spec_and_guard() -> None:
    c = make_codec("pdr:0.8:100:0.8:30:30:C1.0", dof=2)
    assert c.spec == CREDIT and c.payload_bytes == 10  # pdr's, and the lag it measured (16 bits)
    with pytest.raises(CodecError, match="KAPPA must be in"):
        make_codec("pdr:0.8:100:0.8:30:30:c100")
    with pytest.raises(CodecError, match="KAPPA must be a number"):
        make_codec("pdr:0.8:100:0.8:30:30:cx")
    g = EnergyGuard(DT)
    g.credit(1e-3)
    assert g.margin == pytest.approx(1e-3)
    with pytest.raises(ValueError):
        g.credit(-1e-9)


@pytest.mark.parametrize("delay", [0, 15])
def test_credit_flows_on_a_smooth_loop(delay: int) -> None:
    """Both sides self-credit (``withheld`` > 0: withheld from the reports), the two-port stays >= 0
    (a round trip within CREDIT_MAX_RTT: 2 x 15 + 1 ticks here)."""
    t = np.arange(2000) * DT
    g = np.sin(2 * np.pi * 1.3 * t)
    h = 0.9 * np.sin(2 * np.pi * 1.3 * t + 0.1)
    x = np.stack([np.stack([g, g], 1), np.stack([h, h], 1)], 1)
    two_port, guard_min, credited = _two_port_loop(CREDIT, x, delay, [True, True, False])
    assert credited and two_port >= -1e-12 and guard_min >= -1e-12


def test_credit_in_the_sim_cuts_packets_and_stays_two_port_passive() -> None:
    """Zero delay, protocol scenario (short): the senders model each other's self-credit exactly (the
    guards never cut), the two-port energy stays >= 0, and far fewer packets than pdr's split point."""
    s = run_case(SimConfig(codec=CREDIT, scenario="protocol", duration=4.0)).summary
    ref = run_case(SimConfig(codec="pdr:0.8:100:1:128:86", scenario="protocol", duration=4.0)).summary
    assert s["two_port_min_energy"] >= -1e-9
    for d in ("forward", "backward"):
        assert s["passivity"][d]["violations"] == 0
        assert s["passivity"][d]["min_margin"] >= -1e-9
        assert s["wire"][d]["packets"] < 0.8 * ref["wire"][d]["packets"], d


@pytest.mark.integration  # a real session: two processes
def test_a_real_self_crediting_session_is_passive_on_the_session_clock(tmp_path: Path) -> None:
    """Two real processes with cKAPPA: the report's eq. (4) on the session clock (each side's energy
    sent by a tick, reported or not) never goes negative, while the margins that count a sender's
    energy only once a packet carrying it was accepted may, by design (teleop.offline.report, Fold._run)."""
    import json
    import subprocess
    import sys

    out = tmp_path / "run"
    r = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "run", "--codec", "pdr:0.8:100:0.8:30:30:c0.5",
         "--duration", "4", "--out", str(out), "--no-plots", "--no-sim"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode in RAN, r.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["two_port_min_energy_clock"] >= -1e-9
    assert "on the session clock" in r.stdout
