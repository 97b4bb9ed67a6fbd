"""The zero-delay frontier (issue 23, item 6): packets per second each way against eq. (7) on the
Section VI protocol, ``teleop sim --scenario protocol`` (2 DoF, 15 s, no impairment).

The target is at most 40 packets/s a direction at ``I`` no worse than ``ids:2``'s, passive under the
impairment matrix of ``tests/test_watchdog_matrix.py``.  This runs the reflection-aware deadband
``pdr`` over a grid of bands (``teleop.control.codecs.reflective``) next to the references, under both
architectures, marks the best ``pdr`` point within ``ids:2``'s ``I`` (``frontier``), and runs that
point through the whole matrix (hold and conceal) on the full duration, with the matrix test's
assertions.

    python -m bench.frontier0 [--out bench/results/frontier0.json] [--duration 15] [--pool]

``--pool`` adds ``pdr``'s two-port accounting (self-credit ``cKAPPA``, ``teleop.control.codecs.reflective``)
to the grid and writes ``bench/results/frontier0_pool.json``.  Such a codec's per-direction margins
(eq. 5) may go negative by design: its matrix verdict is the two-port's energy (eq. 1 via 4) and the
guards' in-band margins, and both verdicts are recorded.

Virtual time only (a few seconds of CPU per case); nothing here measures wall-clock time.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from bench import write_result
from teleop.offline.sim import SimConfig, run_case
from teleop.session.settings import Passivity
from tests.test_watchdog_matrix import IMPAIRMENTS

PDR = (
    "pdr:0.5:1000",
    "pdr:0.6:1000",
    "pdr:0.7:1000",
    "pdr:0.75:1000",
    "pdr:0.8:1000",
    "pdr:1:1000",
    "pdr:1.5:1000",
    "pdr:0.7",
    "pdr:0.8",
    # Per direction: backward band 1 %, reserve scale 128 % forward and 86 % backward.
    "pdr:0.8:100:1:128:86",
)
REFERENCES = ("none", "ids:2", "pdp:1", "pdp:2")
TDPA = ("none", "pdp:1", "pdr:0.8", "pdr:0.8:100:1:128:86")
#: Two-port accounting (--pool): self-credit at kappa 1 %, bands as pdr:0.8, reserve scales 30 %;
#: and a lower band for a lower I.
TWO_PORT = ("pdr:0.8:100:0.8:30:30:c1", "pdr:0.8:100:0.8:30:30:c0.5", "pdr:0.6:100:0.6:30:30:c1")


def _two_port(codec: str) -> bool:
    """Whether ``codec`` keeps the channel passive as a two-port (pdr's cKAPPA) rather than
    per direction."""
    return codec.startswith("pdr") and len(codec.split(":")) >= 7


TARGET_PPS = 40.0


def _case(codec: str, duration: float, passivity: Passivity = Passivity.WAVE) -> dict[str, Any]:
    s = run_case(SimConfig(codec=codec, scenario="protocol", duration=duration, passivity=passivity)).summary
    return {
        "codec": codec,
        "passivity": passivity,
        "I": s["I"],
        "I_dc": s["I_dc"],
        "packets_per_s": {d: s["wire"][d]["packets"] / duration for d in ("forward", "backward")},
        "passive": s["passive"],
        "min_energy_margin": s["min_energy_margin"],
        "violations": {d: s["passivity"][d]["violations"] for d in ("forward", "backward")},
    }


def _matrix(codec: str, duration: float) -> list[dict[str, Any]]:
    out = []
    for on_loss in ("hold", "conceal"):
        for name, imp in IMPAIRMENTS:
            spec = str(imp.get("netem", ""))
            r = run_case(
                SimConfig(
                    codec=codec,
                    delay_ms=float(imp.get("delay_ms", 0.0)),
                    netem_forward=spec,
                    netem_backward=spec,
                    duration=duration,
                    scenario="protocol",
                    seed=11,
                    on_loss=on_loss,
                )
            )
            s, tr = r.summary, r.trace
            pv = s["passivity"]
            peak = float(max(np.abs(a).max() for a in (tr.v_hsi, tr.v_to, tr.f_hsi, tr.f_to)))
            two_port = (
                s["two_port_min_energy"] >= -1e-9
                and all(pv[d]["min_margin"] >= -1e-9 for d in pv)
                and all(pv[d]["controller_active_ticks"] == pv[d]["violations"] for d in pv)
                and math.isfinite(peak)
                and peak < 50.0
            )
            per_direction = two_port and s["min_energy_margin"] >= -1e-9 and bool(s["passive"])
            ok = two_port if _two_port(codec) else per_direction
            out.append(
                {
                    "impairment": name,
                    "on_loss": on_loss,
                    "passive": ok,
                    "passive_per_direction": per_direction,
                    "passive_two_port": two_port,
                    "violations": {d: pv[d]["violations"] for d in pv},
                    "min_energy_margin": s["min_energy_margin"],
                    "two_port_min_energy": s["two_port_min_energy"],
                    "controller_active_ticks": {d: pv[d]["controller_active_ticks"] for d in pv},
                    "energy_dissipated": s["energy_dissipated"]["total"],
                    "max_abs": peak,
                    "I": s["I"],
                }
            )
    return out


def run(duration: float, pool: bool = False) -> dict[str, Any]:
    cases = [_case(c, duration) for c in (*REFERENCES, *PDR, *(TWO_PORT if pool else ()))]
    cases += [_case(c, duration, Passivity.TDPA) for c in TDPA]
    ids2 = next(c for c in cases if c["codec"] == "ids:2")
    pdr = [c for c in cases if c["codec"].startswith("pdr") and c["passivity"] == Passivity.WAVE]
    within = [c for c in pdr if c["I"] <= ids2["I"]]
    # The fewest packets within ids:2's I, else (a short run) the lowest I.
    if within:
        best = min(within, key=lambda c: max(c["packets_per_s"].values()))
    else:
        best = min(pdr, key=lambda c: c["I"])
    matrix = _matrix(best["codec"], duration)
    return {
        "scenario": "protocol",
        "duration": duration,
        "target": {"packets_per_s": TARGET_PPS, "I": ids2["I"], "I_from": "ids:2"},
        "cases": cases,
        "frontier": {
            **best,
            "max_packets_per_s": max(best["packets_per_s"].values()),
            "target_met": max(best["packets_per_s"].values()) <= TARGET_PPS and best["I"] <= ids2["I"],
            "matrix_passive": all(m["passive"] for m in matrix),
        },
        "matrix": matrix,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="default bench/results/frontier0[_pool].json")
    ap.add_argument("--duration", type=float, default=15.0)
    ap.add_argument("--pool", action="store_true", help="add pdr's two-port accounting (cKAPPA) to the grid")
    a = ap.parse_args()
    if a.out is None:
        a.out = Path("bench/results/frontier0_pool.json" if a.pool else "bench/results/frontier0.json")
    doc = run(a.duration, a.pool)
    write_result(a.out, doc, indent=1)
    f = doc["frontier"]
    pps = f["packets_per_s"]
    print(
        f"frontier {f['codec']}: {pps['forward']:.1f}/{pps['backward']:.1f} packets/s, I = {f['I']:.4e} "
        f"(ids:2 {doc['target']['I']:.4e}), I_dc = {f['I_dc']:.4e}; target met: {f['target_met']}; "
        f"passive under the matrix ({len(doc['matrix'])} cases, {a.duration:g} s): {f['matrix_passive']}"
    )


if __name__ == "__main__":
    main()
