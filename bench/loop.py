"""Loop timing: the operator's and teleoperator's full 1 kHz ticks against an empty reference loop.

The reference runs the same scheduler (``transport.realtime.Ticker``, same spin, same real-time
setup, one event-loop pass per tick) with nothing to do, as a third process *at the same time* as
a real ``teleop run``: a shared VM's stalls hit all three alike, so the ratio of the full loop's
period error to the empty loop's is what the stack itself costs.  Also reports CPU per process.

    python -m bench.loop [--duration S] [--codec SPEC] [--out FILE]

Targets (issue 3): full-loop p99 period error within 1.5x the empty loop's and under 2% of the
period (20 us); CPU at most 25% of a core per process.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from transport.realtime import Ticker, setup_realtime
from transport.udp import new_event_loop


async def _empty_loop(duration: float, spin_us: int, fixed_spin: bool = False) -> dict[str, Any]:
    min_spin = spin_us * 1000 if fixed_spin else 10_000
    ticker = Ticker(spin_ns=spin_us * 1000, capacity=int(duration * 1000) + 16, min_spin_ns=min_spin)
    ticker.start(time.monotonic_ns() + 50_000_000)
    n = int(duration * 1000)
    while ticker.k < n:
        ticker.wait()
        await asyncio.sleep(0)
    return ticker.stats().summary()


def run_empty(duration: float, spin_us: int, out: Path, fixed_spin: bool = False) -> None:
    """The empty loop; ``fixed_spin``: always spin ``spin_us`` (the scheduler before issue 22)."""
    warnings = setup_realtime(10)
    loop, name = new_event_loop()
    try:
        summary = loop.run_until_complete(_empty_loop(duration, spin_us, fixed_spin))
    finally:
        loop.close()
    out.write_text(json.dumps({**summary, "event_loop": name, "warnings": warnings}))


def _pick(loop: dict[str, Any]) -> dict[str, Any]:
    return {
        "ticks": loop["ticks"],
        "overruns": loop["overruns"],
        "skipped": loop["skipped"],
        "period_error_us": loop["period_error_us"],
        "lateness_us": loop["lateness_us"],
        "cpu_fraction": loop["cpu_fraction"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=15.0)
    ap.add_argument("--codec", default="eds:50")
    ap.add_argument("--spin-us", type=int, default=100)
    ap.add_argument("--out", default="bench/results/loop.json")
    ap.add_argument("--empty-only", metavar="FILE", help=argparse.SUPPRESS)
    ap.add_argument("--fixed-spin", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.empty_only:
        run_empty(a.duration, a.spin_us, Path(a.empty_only), a.fixed_spin)
        return
    with tempfile.TemporaryDirectory() as tmp:
        empty_json = Path(tmp) / "empty.json"
        run_dir = Path(tmp) / "run"
        # The session needs ~0.8 s to start; start the empty loop so the two overlap almost fully.
        ref = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "bench.loop",
                "--empty-only",
                str(empty_json),
                "--duration",
                str(a.duration),
                "--spin-us",
                str(a.spin_us),
            ]
        )
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "teleop.cli",
                "run",
                "--codec",
                a.codec,
                "--duration",
                str(a.duration),
                "--out",
                str(run_dir),
                "--no-plots",
                "--no-sim",
            ],
            capture_output=True,
            text=True,
        )
        ref.wait(timeout=a.duration + 30)
        if r.returncode != 0:
            sys.exit(f"teleop run failed: {r.stderr}")
        empty = json.loads(empty_json.read_text())
        rep = json.loads((run_dir / "report.json").read_text())
    res: dict[str, Any] = {
        "what": "1 kHz loop timing, full ticks vs an empty reference loop, same scheduler, same run",
        "duration_s": a.duration,
        "codec": a.codec,
        "scenario": rep["scenario"],
        "python": platform.python_version(),
        "event_loop": empty["event_loop"],
        "rt_warnings": empty["warnings"],
        "empty": _pick(empty),
    }
    p99_empty = empty["period_error_us"]["p99"]
    for role in ("operator", "teleoperator"):
        loop = rep["processes"][role]["loop"]
        p99 = loop["period_error_us"]["p99"]
        res[role] = {
            **_pick(loop),
            "p99_ratio_to_empty": p99 / p99_empty if p99_empty > 0 else None,
            "p99_fraction_of_period": p99 / 1000.0,
            "targets_met": {
                "p99_within_1.5x_empty": p99 <= 1.5 * p99_empty,
                "p99_under_2pct": p99 < 20.0,
                "cpu_at_most_25pct": loop["cpu_fraction"] <= 0.25,
            },
        }
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2) + "\n")
    for name in ("empty", "operator", "teleoperator"):
        x = res[name]
        pe = x["period_error_us"]
        print(
            f"{name:<13} period error p50 {pe['p50']:6.2f}  p99 {pe['p99']:7.2f}  p99.9 {pe['p999']:8.2f}  "
            f"max {pe['max']:8.1f} us  overruns {x['overruns']:3d}  CPU {100 * x['cpu_fraction']:5.1f}%"
        )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
