"""The loop's long pauses that the stack makes, not the host (issue 22, the period-error target).

A tick late by a millisecond is an overrun whatever made it late; on a shared VM most are the
host's, but some were the stack's own: the cyclic GC (set off by the playout buffer's per-payload
tuples; a collection while ticking took up to ~0.5 ms, and a full one would walk every object of
the imports, ~10 ms in-process), the record's chunk seal in the tick (~0.5-1 ms once a second), and
the loop's streaming percentiles giving up their exact samples 65.5 s into a session (four at once
in the ticker: 150-280 ms, hundreds of skipped ticks).  This runs ``teleop run`` (UDP, log on,
``none`` at 2 DoF, 70 s by default, so past tick 65 536) with a probe in each process
(``bench._gc_probe``: every collection of the cyclic GC while it ticks) and reads each process's
per-tick record from its MCAP log.  Per process: overruns, skipped ticks, the largest period
error, ticks late by over 1 ms (and how many a minute), the longest pause between two ticks run
from tick 65 530 to 65 830 and the ticks skipped there, and the GC's collections while ticking, per
generation (count, longest).

``--reference DIR`` (a checkout of another commit) runs the same from it, the order alternated
round by round; the logs of both are read with this tree's reader (the same MCAP layout).

    python -m bench.stalls [--duration S] [--rounds N] [--reference DIR] [--out FILE]

Run it on a quiet host: what the host adds lands in the same figures (the GC's columns are the
stack's alone; a pause of 100 ms or more at tick 65 536 in every process is the percentiles').
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from bench._probed_run import probed_run
from bench.cpu import _commit
from teleop.offline.logfile import read_log

ROOT = Path(__file__).resolve().parent.parent
ROLES = ("operator", "teleoperator")
#: Samples a ``teleop.session.link.quantiles.Quantiles`` keeps exactly (its default ``exact``): the ticker's
#: fill at this tick.  The window read after it covers a stall and the loop's catch-up.
QUANTILE_FILL = 1 << 16
WINDOW = (QUANTILE_FILL - 6, QUANTILE_FILL + 294)
SITE = """import os, sys
if os.environ.get("TELEOP_GC_PROBE"):
    sys.path.insert(0, {bench!r})
    import _gc_probe
    _gc_probe.install(os.environ["TELEOP_GC_PROBE"])
"""


def process_figures(
    loop: dict[str, Any], arrays: dict[str, npt.NDArray[Any]], gc_log: list[list[float]]
) -> dict[str, Any]:
    """One process's figures from its report's loop block, its log's arrays and the GC probe's file.

    The pause around tick 65 536 is read from when each tick played (``play_time_s``, the session
    clock, NaN for a tick not run), not from the lateness: a stall past ``max_catchup`` ticks makes
    the loop skip them, and the lateness it records after the skip is what is left of a period."""
    late = np.asarray(arrays["lateness_ns"], dtype=np.float64) / 1e3
    played = np.asarray(arrays["play_time_s"], dtype=np.float64)
    w = played[WINDOW[0] : WINDOW[1]]
    ran = w[~np.isnan(w)]
    gens: dict[str, Any] = {}
    for g in (0, 1, 2):
        us = [d for gen, d in gc_log if gen == g]
        gens[str(g)] = {"count": len(us), "max_us": max(us, default=0.0), "total_ms": sum(us) / 1e3}
    minutes = late.size / 60_000
    return {
        "ticks": loop["ticks"],
        "overruns": loop["overruns"],
        "skipped": loop["skipped"],
        "period_error_max_us": loop["period_error_us"]["max"],
        "late_over_1ms": int((late > 1000).sum()),
        "late_over_1ms_per_min": float((late > 1000).sum() / minutes) if minutes else 0.0,
        "lateness_max_us": float(late.max()) if late.size else 0.0,
        "at_quantile_fill": (
            {
                # The longest time between two ticks run, less the period: 0 when every tick ran on time.
                "longest_pause_us": float((np.diff(ran).max() - 1e-3) * 1e6),
                "skipped": int(np.isnan(w).sum()),
            }
            if ran.size > 1
            else None
        ),
        "gc_while_ticking": gens,
    }


def run_tree(root: Path, codec: str, dof: int, duration: float, tmp: Path, name: str) -> dict[str, Any]:
    """One ``teleop run`` from ``root``'s tree with the GC probe; each process's figures."""
    site, probe, run_dir = tmp / f"site-{name}", tmp / f"probe-{name}", tmp / f"run-{name}"
    site.mkdir()
    probe.mkdir()
    (site / "sitecustomize.py").write_text(SITE.format(bench=str(ROOT / "bench")))
    probe_env = {"TELEOP_GC_PROBE": str(probe)}
    report = probed_run(root, site, probe_env, codec, dof, duration, run_dir)
    out: dict[str, Any] = {}
    for role in ROLES:
        proc = report["processes"][role]
        _, arrays = read_log(run_dir / "logs" / f"{role}.mcap")
        gc_file = probe / f"gc-{proc['pid']}.json"
        gc_log = json.loads(gc_file.read_text()) if gc_file.is_file() else []
        out[role] = {"pid": proc["pid"], **process_figures(proc["loop"], arrays, gc_log)}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.stalls", description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=70.0, help="seconds per session (default 70)")
    ap.add_argument("--codec", default="none")
    ap.add_argument("--dof", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=1, help="sessions per tree (default 1)")
    ap.add_argument("--reference", type=Path, help="a checkout of another commit, run alternately")
    ap.add_argument("--out", default="bench/results/stalls.json")
    a = ap.parse_args(argv)
    if not 0 < a.duration < float("inf") or a.rounds < 1:
        ap.error("--duration must be a number of seconds > 0, and --rounds an integer >= 1")
    ref = a.reference.resolve() if a.reference is not None else None
    if ref is not None and not (ref / "teleop" / "cli").is_dir():
        ap.error(f"--reference {a.reference}: not a checkout of this project (no teleop/cli in it)")
    trees = [("this", ROOT)] + ([("reference", ref)] if ref is not None else [])
    started = time.time()
    runs = []
    with tempfile.TemporaryDirectory(prefix="teleop-stalls-") as t:
        for i in range(a.rounds):
            for label, root in trees if i % 2 == 0 else trees[::-1]:
                print(f"round {i + 1}: teleop run from {label} ...", flush=True)
                figs = run_tree(root, a.codec, a.dof, a.duration, Path(t), f"{label}-{i}")
                runs.append({"tree": label, "commit": _commit(root), "round": i, **figs})
    doc = {
        "what": "ticks the stack made late: overruns, the GC while ticking, the 65.5 s percentile fill",
        "codec": a.codec,
        "dof": a.dof,
        "duration_s": a.duration,
        "python": platform.python_version(),
        "window_ticks": list(WINDOW),
        "runs": runs,
        "wall_s": round(time.time() - started, 1),
    }
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=2) + "\n")
    for run in runs:
        for role in ROLES:
            x = run[role]
            g = x["gc_while_ticking"]
            fill = x["at_quantile_fill"] or {"longest_pause_us": float("nan")}
            print(
                f"{run['tree']:<9} {run['commit'][:7]} {role:<12} overruns {x['overruns']:4d}  skipped"
                f" {x['skipped']:4d}  max period error {x['period_error_max_us'] / 1e3:7.1f} ms  late >1 ms"
                f" {x['late_over_1ms_per_min']:6.1f}/min"
                f"  pause at 65.5 s {fill['longest_pause_us'] / 1e3:6.1f} ms"
                f"  GC while ticking {g['0']['count']}/{g['1']['count']}/{g['2']['count']}"
                f" (longest {max(v['max_us'] for v in g.values()) / 1e3:.2f} ms)"
            )
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
