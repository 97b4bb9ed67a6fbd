"""Real-time transparency against the simulation: I_run / I_sim per codec, transport and impairment.

For each case, ``teleop run`` (two real processes on loopback, default settings otherwise) and its
report's ``teleop sim`` of the same settings (same scenario, codec, impairment, seeds, passivity
options): the ratio ``I_run / I_sim`` of eq. (7), the median over ``--runs`` runs, with the payloads
that missed their tick (each one a concealed tick) and the link-lost events.  Issue 13's target:
median ratio at most 1.5 for every codec over UDP with no impairment, at most 2 over Zenoh.  Beside
it, ``I_run / I_replay`` (issue 37): the report's sim once more with the run's own deliveries (each
payload at the tick the real receiver took it), 1 where the code paths agree, whatever the host did.

    python -m bench.rt_transparency [--runs 3] [--duration 5] [--transport udp zenoh]
        [--codec SPEC ...] [--netem SPEC ...] [--out bench/results/rt_transparency.json]

Do not run it next to another heavy process: the real runs are what it measures.
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench import write_result

CODECS = ("none", "ids:2", "ids:50", "eds:2", "eds:50", "cq:8")  # the paper's Section V set
IMPAIRMENTS = ("", "loss 2%", "delay 20ms 5ms")


def one_run(
    codec: str, transport: str, netem: str, duration: float, out: Path, playout: str = "auto"
) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "teleop.cli", "run", "--codec", codec, "--transport", transport]
    cmd += ["--playout", playout]
    cmd += ["--duration", repr(duration), "--out", str(out), "--no-plots", "--no-live"]
    cmd += ["--netem", netem] if netem else []
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=duration * 4 + 60)
    if r.returncode not in (0, 3):  # 3: a poor session (teleop.session.verdict): it ran, measured
        return {"error": (r.stderr or r.stdout).strip().splitlines()[-1:]}
    rep = json.loads((out / "report.json").read_text())
    if rep["codec"] != codec or rep["transport"] != transport:
        return {"error": [f"{out} holds another run's report"]}
    tr = rep["transparency"]
    return {
        "I_run": tr["I"],
        "I_sim": tr["I_sim"],
        "ratio": tr["I"] / tr["I_sim"] if tr["I_sim"] else None,
        "I_replay": (tr.get("replay") or {}).get("I"),
        "replay_ratio": tr["I_over_sim_s"] / tr["replay"]["I"] if (tr.get("replay") or {}).get("I") else None,
        "missed": sum(p["grace"]["missed"] for p in rep["processes"].values()),
        "link_lost": sum(rep["passivity"][d]["link_lost_events"] for d in ("forward", "backward")),
        "min_margin": min(rep["energy"][d]["min_margin"] for d in ("forward", "backward")),
        "playout": {d: rep["playout"][d] for d in ("forward", "backward")},
        "stale": sum(p["inbound"]["stale"] for p in rep["processes"].values()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--duration", type=float, default=5.0)
    ap.add_argument("--transport", nargs="+", default=["udp", "zenoh"], choices=["udp", "zenoh"])
    ap.add_argument("--codec", nargs="+", default=list(CODECS))
    ap.add_argument("--netem", nargs="+", default=list(IMPAIRMENTS), help='impairments ("" for none)')
    ap.add_argument("--playout", nargs="+", default=["auto"], help="playout settings to compare")
    ap.add_argument("--out", default="bench/results/rt_transparency.json")
    a = ap.parse_args()
    cases: list[dict[str, Any]] = []
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        for transport in a.transport:
            for netem, playout, codec in itertools.product(a.netem, a.playout, a.codec):
                if True:
                    runs = [
                        # A folder per run: a report is never overwritten, so a reused --out
                        # would hold the first case's report.json and this run's under another name.
                        one_run(
                            codec, transport, netem, a.duration, Path(tmp) / f"c{len(cases)}-r{i}", playout
                        )
                        for i in range(a.runs)
                    ]
                    ratios = [r["ratio"] for r in runs if r.get("ratio") is not None]
                    replays = [r["replay_ratio"] for r in runs if r.get("replay_ratio") is not None]
                    case = {
                        "transport": transport,
                        "netem": netem,
                        "codec": codec,
                        "playout": playout,
                        "median_ratio": statistics.median(ratios) if ratios else None,
                        "median_replay_ratio": statistics.median(replays) if replays else None,
                        "I_sim": next((r["I_sim"] for r in runs if "I_sim" in r), None),
                        "runs": runs,
                    }
                    cases.append(case)
                    med = "-" if case["median_ratio"] is None else f"{case['median_ratio']:.2f}"
                    missed = [r.get("missed") for r in runs]
                    print(
                        f"{transport:<6} {netem or 'none':<16} {playout:<5} {codec:<8} "
                        f"I_run/I_sim median {med:>7}  I_run/I_replay {replays}  "
                        f"I_sim {case['I_sim'] if case['I_sim'] is None else format(case['I_sim'], '.3e')}  "
                        f"missed {missed} stale {[r.get('stale') for r in runs]}",
                        flush=True,
                    )
    doc = {
        "what": "I_run / I_sim, median over runs; teleop run vs its report's teleop sim of the same settings",
        "runs": a.runs,
        "duration_s": a.duration,
        "python": platform.python_version(),
        "wall_s": time.monotonic() - t0,
        "cases": cases,
    }
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_result(out, doc)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
