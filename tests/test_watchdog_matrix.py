"""Issue 6's matrix, through `teleop sim` for speed: stay passive under delay, loss, jitter, reordering.

With the controller on and the *worst* reconstruction (hold the last sample on loss, which
generates energy by itself), no case may generate energy: the true margin (energy the sender put
in minus energy the receiver played, per direction, every tick) never drops below -1e-9 J, and the
signals stay bounded.  With the controller off, the same hold under loss must show violations, so
the test also proves the watchdog sees what it must.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from teleop.control.codecs import make_codec
from teleop.offline.sim import SimConfig, run_case

# One of each class: direct, interpolative, extrapolative, then issue 10's deadbands and DCT.
CODECS = ["none", "ids:5", "eds:5", "cq:8", "pd:1", "pdp:1", "dct:20:2"]
#: Codecs whose reconstruction holds between payloads by design: passive only behind the guard.
HOLDING = ("pd:1", "pdp:1")
#: The receivers' reconstructions when nothing is queued: the worst, and the default.
ON_LOSS = ("hold", "conceal")


def on_loss_cases(codecs: list[str]) -> list[tuple[str, str]]:
    """Each codec with each ``on_loss``, less "conceal" for the deadbands (and pdr, in
    tests/test_codec_pdr.py): their decoders never read ``on_loss``
    (test_a_deadbands_reconstruction_ignores_on_loss), so a "conceal" run would repeat the "hold"
    run tick for tick (measured: the same summary in each of their 12 cases)."""
    return [(c, o) for c in codecs for o in ON_LOSS if o == "hold" or c not in HOLDING]


IMPAIRMENTS: list[tuple[str, dict[str, Any]]] = [
    ("delay 0", {"delay_ms": 0.0}),
    ("delay 10", {"delay_ms": 10.0}),
    ("delay 100", {"delay_ms": 100.0}),
    ("delay 500", {"delay_ms": 500.0}),
    ("jitter", {"netem": "delay 20ms 10ms"}),  # without rate, jitter reorders
    ("reorder", {"netem": "delay 10ms reorder 25% gap 5"}),
    ("loss 1%", {"netem": "loss 1%"}),
    ("loss 10%", {"netem": "delay 5ms loss 10%"}),
    ("loss 30%", {"netem": "loss 30%"}),
    ("bursts", {"netem": "loss gemodel 5% 20%"}),  # Gilbert-Elliott: mean burst 5 packets
    ("duplicate", {"netem": "delay 5ms 2ms duplicate 20%"}),
    ("rate cap", {"netem": "rate 300kbit"}),
]


def run(codec: str, imp: dict[str, Any], **kw: Any) -> dict[str, Any]:
    spec = imp.get("netem", "")
    cfg = SimConfig(
        codec=codec,
        delay_ms=imp.get("delay_ms", 0.0),
        netem_forward=spec,
        netem_backward=spec,
        duration=1.5 if imp.get("delay_ms", 0.0) < 500 else 2.5,
        scenario="protocol",
        seed=11,
        **kw,
    )
    r = run_case(cfg)
    tr = r.trace
    s: dict[str, Any] = r.summary
    s["max_abs"] = float(
        max(np.abs(tr.v_hsi).max(), np.abs(tr.v_to).max(), np.abs(tr.f_hsi).max(), np.abs(tr.f_to).max())
    )
    return s


@pytest.mark.parametrize("name,imp", IMPAIRMENTS, ids=[n for n, _ in IMPAIRMENTS])
@pytest.mark.parametrize(("codec", "on_loss"), on_loss_cases(CODECS))
def test_controller_keeps_every_case_passive(
    codec: str, name: str, imp: dict[str, Any], on_loss: str
) -> None:
    s = run(codec, imp, on_loss=on_loss, controller=True)
    assert s["min_energy_margin"] >= -1e-9, (s["energy"], s["passivity"])
    assert s["two_port_min_energy"] >= -1e-9  # eq. (4): the whole two-port never gives energy back
    assert s["passive"]
    for d in ("forward", "backward"):
        pv = s["passivity"][d]
        assert pv["min_margin"] >= -1e-9  # the watchdog's in-band view, after the controller
        assert pv["controller_active_ticks"] == pv["violations"]  # it acted on every violation it saw
    assert np.isfinite(s["max_abs"]) and s["max_abs"] < 50.0  # bounded (the protocol peaks near 5 N)


@settings(max_examples=60, deadline=None)
@given(
    spec=st.sampled_from([*HOLDING, "pd:5", "pdp:5", "pdr:0.8", "pdr:0.8:100:1:128:86"]),
    x=arrays(np.float64, (80, 2), elements=st.floats(-2.0, 2.0)),
    keep=st.lists(st.booleans(), min_size=80, max_size=80),
)
def test_a_deadbands_reconstruction_ignores_on_loss(spec: str, x: np.ndarray, keep: list[bool]) -> None:
    """Why the matrices run the deadbands (and pdr) with "hold" only: whatever payloads are lost,
    their decoders play the same samples, bit for bit, whichever ``on_loss`` they were given."""
    c = make_codec(spec, dof=2, full_scale=2.0)
    enc = c.encoder()
    decoders = [c.decoder(on_loss=o) for o in ("hold", "conceal", "zero")]
    for i in range(len(x)):
        payload = enc.encode(x[i])
        if payload is not None and keep[i]:
            for d in decoders:
                d.push(payload)
        played = [d.next() for d in decoders]
        assert all(np.array_equal(played[0], p) for p in played[1:]), (i, played)
    assert all(d.underruns == decoders[0].underruns for d in decoders)


@pytest.mark.parametrize("spec", ["loss 10%", "loss gemodel 5% 20%", "delay 10ms 5ms"])
@pytest.mark.parametrize("codec", CODECS)
def test_without_controller_hold_violates_and_the_watchdog_sees_it(codec: str, spec: str) -> None:
    # Without the playout buffer, so that reordered payloads are dropped and their gaps held.
    s = run(codec, {"netem": spec}, on_loss="hold", controller=False, playout="off")
    seen = sum(s["passivity"][d]["violations"] for d in ("forward", "backward"))
    assert seen > 0
    assert min(s["passivity"][d]["min_margin"] for d in ("forward", "backward")) < -1e-9
    assert all(s["passivity"][d]["controller_active_ticks"] == 0 for d in ("forward", "backward"))


@pytest.mark.parametrize("codec", [c for c in CODECS if c not in HOLDING])
def test_zero_fill_needs_no_controller(codec: str) -> None:
    """Zero on loss and dropping stale packets are passive by themselves: the watchdog sees nothing.

    Not for the deadbands: they hold between payloads whatever ``on_loss`` says, and a hold is
    passive only within the budget the guard enforces (``teleop.control.codecs.deadband``)."""
    s = run(codec, {"netem": "delay 10ms 5ms loss 10% duplicate 5%"}, on_loss="zero", controller=False)
    assert s["min_energy_margin"] >= -1e-9
    assert all(s["passivity"][d]["violations"] == 0 for d in ("forward", "backward"))


def test_outage_goes_to_safe_state_and_recovers(tmp_path: Path) -> None:
    """A 300 ms outage (a trace link with no delivery opportunity from 500 to 800 ms): both sides go
    to the safe state once, resume when the held-back packets arrive, and stay passive."""
    trace = tmp_path / "outage.trace"
    trace.write_text("\n".join(str(t) for t in [*range(0, 500), *range(800, 3000)]) + "\n")
    s = run("none", {"netem": f"trace {trace}"}, link_timeout=0.05)
    for d in ("forward", "backward"):
        pv = s["passivity"][d]
        assert pv["link_lost_events"] == 1, d
        assert 150 <= pv["link_lost_ticks"] <= 300, d  # 300 ms of silence minus the 50 ms timeout
    assert s["min_energy_margin"] >= -1e-9


@pytest.mark.parametrize("spec", ["loss 10%", "loss gemodel 5% 20%", "delay 20ms 5ms"])
@pytest.mark.parametrize("codec", ["none", "eds:5"])
def test_concealment_beats_zero_fill(codec: str, spec: str) -> None:
    """Issue 13: playing a budgeted, fading hold instead of zero on a missing sample is far more
    transparent under loss and jitter, and stays passive."""
    zero = run(codec, {"netem": spec}, on_loss="zero", playout="off")
    conceal = run(codec, {"netem": spec}, on_loss="conceal", playout="off")
    assert conceal["passive"] and conceal["I"] < 0.5 * zero["I"], (conceal["I"], zero["I"])
