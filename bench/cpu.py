"""CPU of the 1 kHz loop against the floor reference, in one invocation on one host (issue 22).

Runs, one after the other:

1. the floor reference (``bench.floor``: a pair of processes that sleep to 100 us before each
   deadline, spin the rest, seal a 40-byte body with keyed BLAKE2s, send it to the other over
   loopback UDP, drain and verify what arrived);
2. ``teleop run`` (``protocol`` scenario, UDP, authenticated, no log) for ``none``, ``eds:50`` and
   ``pdp:1`` at 2 and 6 DoF and ``none`` at 64 DoF, each with an empty reference loop
   (``bench.loop``'s: the same scheduler with today's fixed 100 us spin and nothing to do) running
   alongside, so a stall of the shared host hits both;
3. the floor again: the figure each ratio divides by is the mean of the four floor processes.

Per process: CPU % (``loop.cpu_fraction`` of the report), its ratio to the floor, period-error
p99 and p99.9 and their ratio to the empty loop's, and the port's per-tick cost of that side
(``bench.tick.bench_port_sides``, no I/O).  Targets: CPU at most 1.5x the floor at 2 and 6 DoF and
2x at 64 DoF; the port's tick at most 15 us per side at 2 DoF with ``none``.

    python -m bench.cpu [--duration S] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.tick import bench_port_sides

CASES: tuple[tuple[str, int], ...] = (
    ("none", 2),
    ("eds:50", 2),
    ("pdp:1", 2),
    ("none", 6),
    ("eds:50", 6),
    ("pdp:1", 6),
    ("none", 64),
)
ROLES = ("operator", "teleoperator")
EMPTY_SPIN_US = 100  # the scheduler's spin before issue 22: the empty loop keeps it as the yardstick


def cpu_target(dof: int) -> float:
    return 2.0 if dof >= 64 else 1.5


def run_floor(duration: float, tmp: Path, name: str) -> dict[str, Any]:
    out = tmp / f"{name}.json"
    subprocess.run(
        [sys.executable, "-m", "bench.floor", "--duration", str(duration), "--out", str(out)], check=True
    )
    res: dict[str, Any] = json.loads(out.read_text())
    return res


def run_case(codec: str, dof: int, duration: float, tmp: Path) -> dict[str, Any]:
    """One ``teleop run`` with an empty loop alongside; the two processes' loop figures and the empty's."""
    name = f"{codec.replace(':', '')}-{dof}"
    empty_json, run_dir = tmp / f"empty-{name}.json", tmp / f"run-{name}"
    # The session needs ~1 s to start; start the empty loop so the two overlap almost fully.
    ref = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "bench.loop",
            "--empty-only",
            str(empty_json),
            "--duration",
            str(duration),
            "--spin-us",
            str(EMPTY_SPIN_US),
            "--fixed-spin",
        ]
    )
    cmd = [sys.executable, "-m", "teleop.cli", "run", "--codec", codec, "--dof", str(dof)]
    cmd += ["--duration", str(duration), "--out", str(run_dir), "--no-plots", "--no-sim", "--no-live"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    ref.wait(timeout=duration + 60)
    if r.returncode != 0:
        sys.exit(f"teleop run {codec} {dof} DoF failed: {r.stderr}")
    rep = json.loads((run_dir / "report.json").read_text())
    return {"empty": json.loads(empty_json.read_text()), "report": rep}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=10.0, help="seconds per session (default 10)")
    ap.add_argument("--tick-ticks", type=int, default=3000, help="ticks per repeat of the port timing")
    ap.add_argument("--tick-repeats", type=int, default=5)
    ap.add_argument("--out", default="bench/results/cpu.json")
    a = ap.parse_args()
    started = time.time()
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        floors = [run_floor(a.duration, tmp, "floor-before")]
        runs = []
        for codec, dof in CASES:
            print(f"teleop run {codec} {dof} DoF ...", flush=True)
            runs.append((codec, dof, run_case(codec, dof, a.duration, tmp)))
        floors.append(run_floor(a.duration, tmp, "floor-after"))
    floor_cpu = statistics.fmean(s["cpu_fraction"] for f in floors for s in f["sides"])
    cases = []
    for codec, dof, r in runs:
        empty = r["empty"]
        pe_empty = empty["period_error_us"]
        ops, tos = bench_port_sides(codec, dof, a.tick_ticks, a.tick_repeats, scenario="protocol")
        tick_us = {"operator": statistics.median(ops), "teleoperator": statistics.median(tos)}
        case: dict[str, Any] = {
            "codec": codec,
            "dof": dof,
            "empty": {"period_error_us": pe_empty, "cpu_fraction": empty["cpu_fraction"]},
            "cpu_target_ratio": cpu_target(dof),
        }
        for role in ROLES:
            loop = r["report"]["processes"][role]["loop"]
            pe = loop["period_error_us"]
            ratio = loop["cpu_fraction"] / floor_cpu
            case[role] = {
                "cpu_fraction": loop["cpu_fraction"],
                "cpu_ratio_to_floor": ratio,
                "period_error_us": {"p99": pe["p99"], "p999": pe["p999"], "max": pe["max"]},
                "p99_ratio_to_empty": pe["p99"] / pe_empty["p99"] if pe_empty["p99"] > 0 else None,
                "p999_ratio_to_empty": pe["p999"] / pe_empty["p999"] if pe_empty["p999"] > 0 else None,
                "overruns": loop["overruns"],
                "skipped": loop["skipped"],
                "port_tick_us": tick_us[role],
                "cpu_target_met": ratio <= cpu_target(dof),
            }
        cases.append(case)
    tick_2 = next(c for c in cases if c["codec"] == "none" and c["dof"] == 2)
    targets = {
        "cpu": {"met": sum(c[role]["cpu_target_met"] for c in cases for role in ROLES), "of": 2 * len(cases)},
        "port_tick_15us_none_2dof": {
            "met": sum(tick_2[role]["port_tick_us"] <= 15.0 for role in ROLES),
            "of": 2,
        },
    }
    res: dict[str, Any] = {
        "what": "CPU per process of teleop run against the floor reference, same invocation, same host",
        "duration_s": a.duration,
        "scenario": "protocol",
        "python": platform.python_version(),
        "machine": platform.machine(),
        "empty_loop_spin_us": EMPTY_SPIN_US,
        "floor": {"cpu_fraction": floor_cpu, "runs": floors},
        "cases": cases,
        "targets": targets,
        "wall_s": time.time() - started,
    }
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2) + "\n")
    print(f"floor: CPU {100 * floor_cpu:.1f}% per process")
    for c in cases:
        for role in ROLES:
            x, pe_empty = c[role], c["empty"]["period_error_us"]
            print(
                f"{c['codec']:<7} {c['dof']:>2} DoF {role:<12} CPU {100 * x['cpu_fraction']:5.1f}% "
                f"({x['cpu_ratio_to_floor']:.2f}x floor, target {c['cpu_target_ratio']:g}x)  "
                f"p99 {x['period_error_us']['p99']:7.1f} us (empty {pe_empty['p99']:6.1f})  "
                f"p99.9 {x['period_error_us']['p999']:7.1f} us  port tick {x['port_tick_us']:6.1f} us"
            )
    print(
        f"targets: CPU {targets['cpu']['met']}/{targets['cpu']['of']}, port tick "
        f"{targets['port_tick_15us_none_2dof']['met']}/2; wrote {out}"
    )


if __name__ == "__main__":
    main()
