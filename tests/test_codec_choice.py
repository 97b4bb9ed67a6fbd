"""What a user picks a codec by: presets, named parameters, ``--help``, and the sweep's default grid.

A preset or named parameters resolve to the canonical positional spec, the only form a hello
carries (PROTOCOL.md 3.5); the sweep's default grid holds every point of the measured front, so the
front a user draws with ``teleop sweep`` is the one the docs report.
"""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import pytest

from teleop.control.codecs import ACCEPTED, GRAMMARS, PRESETS, CodecError, CodecSpec, expand, make_codec
from teleop.offline.sweep import DEFAULT_GRID, pareto_flags
from teleop.session.protocol import ProtocolError, SessionParams

ROOT = Path(__file__).resolve().parent.parent
LOW_RATE = "pdr:0.8:100:0.8:30:30:c0.5"


def test_presets_resolve_to_canonical_specs() -> None:
    assert CodecSpec.parse("low-rate") == LOW_RATE
    assert CodecSpec.parse("LOW-RATE") == LOW_RATE
    assert CodecSpec.parse("tdpa") == "pdp:5"
    assert [str(s) for s in expand("paper")] == list(PRESETS["paper"])
    with pytest.raises(CodecError, match="names 6 codecs"):
        CodecSpec.parse("paper")  # a command that runs one codec


@pytest.mark.parametrize(
    ("named", "positional"),
    [
        ("pdr:pct=0.8,bpct=0.8,fr=30,br=30,kappa=0.5", LOW_RATE),
        ("pdr:kappa=0.5,br=30,fr=30,pct=0.8", LOW_RATE),  # any order; bpct defaults to pct
        ("pdr:pct=0.8,maxms=100", "pdr:0.8"),
        ("pdr:pct=0.8,bpct=1,fr=128,br=86", "pdr:0.8:100:1:128:86"),
        ("eds:k=50", "eds:50"),
        ("cq:bits=8,range=1.5", "cq:8:1.5"),
        ("dct:n=20,m=2", "dct:20:2"),
        ("pd:pct=5,maxms=20", "pd:5:20"),
    ],
)
def test_named_parameters_mean_the_positional_spec(named: str, positional: str) -> None:
    spec = CodecSpec.parse(named)
    assert spec == positional
    assert spec.values == CodecSpec.parse(positional).values
    assert make_codec(named, 2, 2.0).payload_bytes == make_codec(positional, 2, 2.0).payload_bytes


@pytest.mark.parametrize(
    ("text", "msg"),
    [
        (
            "pdr:pct=0.8,gain=1",
            "'gain=1' is not PARAM=VALUE with PARAM one of pct, maxms, bpct, fr, br, kappa",
        ),
        ("pdr:bpct=1", "pdr needs pct"),
        ("pdr:pct=0.8,pct=1", "pct given twice"),
        ("pdr:pct=200", "PCT must be in"),
        ("eds:k=x", "K must be an integer"),
    ],
)
def test_bad_named_parameters_say_what_is_allowed(text: str, msg: str) -> None:
    with pytest.raises(CodecError, match=msg):
        CodecSpec.parse(text)


def _hello(codec: str) -> dict[str, object]:
    p = SessionParams(
        session=1, codec="eds:50", scenario="protocol", dof=2, b=20.0, full_scale=2.0, duration=1.0
    )
    return {**p.to_msg(), "codec": codec}


def test_the_wire_carries_the_canonical_spec_only() -> None:
    """A preset or named parameters resolve before the hello; a peer's hello with one is refused."""
    local = SessionParams(
        session=1, codec="low-rate", scenario="protocol", dof=2, b=20.0, full_scale=2.0, duration=1.0
    ).validate()
    wire = msgpack.unpackb(msgpack.packb(local.to_msg(), use_bin_type=True), raw=False)
    assert wire["codec"] == LOW_RATE
    assert SessionParams.from_msg(wire).codec == LOW_RATE
    for text in ("low-rate", "pdr:pct=0.8"):
        with pytest.raises(ProtocolError, match="not a wire spec"):
            SessionParams.from_msg(_hello(text))
    with pytest.raises(ProtocolError, match="canonical form 'eds:50'"):  # no longer lenient (issue 49)
        SessionParams.from_msg(_hello("EDS:050"))


def test_help_lists_every_form_and_preset() -> None:
    for grammar, params in GRAMMARS.values():
        assert grammar in ACCEPTED
        for p in params:
            assert p.name in ACCEPTED
    for name in PRESETS:
        assert f"{name}:" in ACCEPTED
    assert "%" not in ACCEPTED  # argparse formats help text with %


@pytest.mark.parametrize("criterion", ["both directions", "busier direction"])
def test_the_default_grid_holds_every_point_of_the_measured_front(criterion: str) -> None:
    """Every Pareto point of the recorded sweep and frontier benches (wave variables), by packets/s
    of both directions or of the busier one (issue 23's per-direction target), is in the grid."""
    cases: dict[str, tuple[float, float]] = {}
    for name in ("sweep/sweep.json", "frontier0.json", "frontier0_pool.json"):
        doc = json.loads((ROOT / "bench" / "results" / name).read_text())
        for c in doc["cases"]:
            if c.get("passivity", "wave") == "wave":
                pps = c["packets_per_s"].values()
                rate = sum(pps) if criterion == "both directions" else max(pps)
                cases[c["codec"]] = (rate, c["I"])
    names = list(cases)
    front = [n for n, on in zip(names, pareto_flags([cases[n] for n in names]), strict=True) if on]
    assert LOW_RATE in front or criterion == "both directions"
    assert set(front) <= set(DEFAULT_GRID), set(front) - set(DEFAULT_GRID)
