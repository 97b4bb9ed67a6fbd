"""Wave variables against TDPA over distance (issue 23): eq. (7), its delay-compensated form, drift,
dissipated energy and packet rates per architecture, codec and link, from ``teleop sim``.

For each link (``--netem`` on both directions) it runs ``teleop sim --scenario protocol`` once per
architecture, wave with ``none`` and ``pdp:1``, TDPA with the codecs of power variables, and keeps
each case's figures.  ``best_tdpa`` is the TDPA case of lowest ``I_dc`` sending at most 100
packets/s a direction; ``ratio`` is its ``I_dc`` over wave ``none``'s (the issue's target: <= 0.5).
``bounded`` compares the largest 1-s RMS of the robot's velocity and force in the last third of the
run with the largest before it (a growing oscillation would make it exceed 1).

    python -m bench.tdpa_delay [--out bench/results/tdpa_delay.json]

Virtual time only (about 1.5 s of CPU per case); nothing here measures wall-clock time.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from bench import write_result

LINKS = {
    "50ms": "delay 50ms",
    "200ms": "delay 200ms",
    # Analog-1-like: mean one-way ~800 ms, Pareto spikes to 3 s (the table's tail is delay + 4 jitter),
    # 5% loss; jitter reorders.
    "analog": "delay 820ms 545ms distribution pareto loss 5%",
}
WAVE = ("none", "pdp:1")
TDPA = ("none", "cq:8", "pd:5", "pd:10", "pdp:1", "pdp:5", "pdp:10")
MAX_PPS = 100.0


def _sim(passivity: str, codecs: tuple[str, ...], netem: str) -> tuple[list[str], dict[str, Any]]:
    with tempfile.TemporaryDirectory() as tmp:
        cmd = ["teleop", "sim", "--scenario", "protocol", "--passivity", passivity, "--netem", netem]
        for c in codecs:
            cmd += ["--codec", c]
        cmd += ["--out", tmp]
        subprocess.run(
            [sys.executable, "-m", "teleop.cli", *cmd[1:]], check=False, capture_output=True, text=True
        )
        return cmd[:-2], json.loads((Path(tmp) / "results.json").read_text())


def _case(c: dict[str, Any], duration: float) -> dict[str, Any]:
    w = c["wire"]
    return {
        "codec": c["codec"],
        "I": c["I"],
        "I_dc": c["I_dc"],
        "delay_compensation_ms": c["delay_compensation_ms"],
        "drift_mm": {k: 1e3 * v for k, v in c["drift_m"].items()},
        "energy_dissipated_J": c["energy_dissipated"],
        "packets_per_s": {d: w[d]["packets"] / duration for d in ("forward", "backward")},
        "passive": c["passive"],
        "min_energy_margin_J": c["min_energy_margin"],
        "link_lost_events": {d: c["passivity"][d]["link_lost_events"] for d in ("forward", "backward")},
        "controller_active_ticks": {
            d: c["passivity"][d]["controller_active_ticks"] for d in ("forward", "backward")
        },
        "link_delay_ms": c["link"]["forward"]["delay_ms"],
        "link_loss": {d: c["link"][d]["loss"] for d in ("forward", "backward")},
        "peak_force_N": c["peak_force_N"],
    }


def _bounded(passivity: str, codec: str, netem: str) -> dict[str, float]:
    """Largest 1-s RMS of v_to and F_to in the last third over the largest before it (run in-process)."""
    from teleop.offline.sim import SimConfig, run_case
    from teleop.session.settings import Passivity

    arch = Passivity.of(passivity)
    tr = run_case(
        SimConfig(codec=codec, scenario="protocol", passivity=arch, netem_forward=netem, netem_backward=netem)
    ).trace
    out = {}
    for name, a in (("v_to", tr.v_to), ("f_to", tr.f_to)):
        n = a.shape[0] // 1000
        rms = np.sqrt((a[: n * 1000] ** 2).reshape(n, 1000, -1).mean(axis=(1, 2)))
        k = 2 * n // 3
        out[name] = float(rms[k:].max() / rms[:k].max())
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="bench/results/tdpa_delay.json")
    args = ap.parse_args()
    doc: dict[str, Any] = {"scenario": "protocol", "max_packets_per_s": MAX_PPS, "links": {}}
    for name, spec in LINKS.items():
        block: dict[str, Any] = {"netem": spec}
        for arch, codecs in (("wave", WAVE), ("tdpa", TDPA)):
            cmd, res = _sim(arch, codecs, spec)
            block[arch] = {"command": " ".join(repr(a) if " " in a else a for a in cmd)}
            block[arch]["cases"] = [_case(c, res["duration"]) for c in res["cases"]]
        ok = [c for c in block["tdpa"]["cases"] if max(c["packets_per_s"].values()) <= MAX_PPS]
        best = min(ok, key=lambda c: c["I_dc"]) if ok else None
        wave_none = block["wave"]["cases"][0]
        block["best_tdpa"] = best["codec"] if best else None
        block["ratio_I_dc_best_tdpa_over_wave_none"] = best["I_dc"] / wave_none["I_dc"] if best else None
        if name == "analog":
            block["bounded"] = {
                "wave none": _bounded("wave", "none", spec),
                "tdpa none": _bounded("tdpa", "none", spec),
            }
        doc["links"][name] = block
        ratio = block["ratio_I_dc_best_tdpa_over_wave_none"]
        best_dc = f"{best['I_dc']:.4g}" if best else "-"
        print(
            f"{name:6} wave none I_dc {wave_none['I_dc']:.4g}  best tdpa <= {MAX_PPS:g}/s: "
            f"{block['best_tdpa']} I_dc {best_dc}  ratio {ratio}",
            flush=True,
        )
    write_result(args.out, doc)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
