"""Where a real process's loop spends its CPU, phase by phase (issue 22).

``bench.cpu`` says how much CPU each ``teleop run`` process takes against the floor; this says
where it goes.  It runs ``teleop run`` (UDP, authenticated, logs on, the ``protocol`` scenario) with
a probe (``bench._phase_probe``) loaded in each process at start, which times the loop's phases
with the thread's CPU clock: the sleep, the spin, the socket's read, the endpoint's receive,
its tick (the port's tick within it), the sends, the log's watch and the events; ``other`` is the
ticking's CPU that no phase took (the event loop's pass each tick and the loop's own lines),
``ticking`` the main thread's CPU over the ticks, ``threads`` the other threads' over the same span
and ``process`` both.  Figures are microseconds of CPU per tick,
with the probe's own clock reads taken off each phase (two per wrapped call); the rest of the
probe's cost (a Python call and two dict updates per wrapped call, about ten a tick) lands in
``other``.

Beside it, each side's port alone (``bench.tick``'s exchange, no I/O) timed two ways: back to back,
as ``bench.tick`` does, and one tick a millisecond on the real loop's scheduler.  A tick that runs
after the loop slept costs several times one that runs hot, and the processes run every tick so.

    python -m bench.phases [--codecs none eds:50 pdp:1] [--dof 2] [--duration 10] [--out FILE]

Run it on a quiet host: it measures time.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench._phase_probe import PHASES
from bench._probed_run import probed_run
from bench.tick import _port_pair, port_side_ticks
from transport.realtime import Ticker

ROOT = Path(__file__).resolve().parent.parent
SITE = """import os
if os.environ.get("TELEOP_PHASES"):
    import bench._phase_probe
    bench._phase_probe.install(os.environ["TELEOP_PHASES"])
"""
NESTED = {"port_tick": "endpoint_tick"}  # a phase inside another: not subtracted twice


def figures(doc: dict[str, Any], ticks: int) -> dict[str, float]:
    """µs of CPU per tick for each phase of one process's probe file, the probe's reads taken off."""
    cpu, calls, read = doc["cpu_ns"], doc["calls"], doc["clock_read_ns"]

    def net(key: str) -> float:
        # A wrapped call reads the clock twice; calls nested in it add their own two reads to it.
        inner = sum(calls.get(k, 0) for k, parent in NESTED.items() if parent == key)
        return float(cpu.get(key, 0) - 2 * read * (calls.get(key, 0) + inner)) / ticks / 1e3

    phases = {key: net(key) for _, _, _, key, _ in PHASES if key != "ticks"}
    wrapped_in_ticks = sum(calls.get(k, 0) for _, _, _, k, _ in PHASES if k != "ticks")
    ticking = (cpu.get("ticks", 0) - 2 * read * (calls.get("ticks", 0) + wrapped_in_ticks)) / ticks / 1e3
    top = sum(v for k, v in phases.items() if k not in NESTED)
    return {
        **{k: round(v, 2) for k, v in phases.items()},
        "other": round(ticking - top, 2),
        "ticking": round(ticking, 2),
        # The process's CPU over the ticking, every thread (the log's feeder, Zenoh's if any).
        "process": round(cpu.get("ticks_process", 0) / ticks / 1e3, 2),
        "threads": round((cpu.get("ticks_process", 0) - cpu.get("ticks", 0)) / ticks / 1e3, 2),
    }


def _spun() -> Callable[[], None]:
    """A wait that busy-waits to the next millisecond: paced like the loop, but never idle."""
    deadline = time.perf_counter_ns()

    def wait() -> None:
        nonlocal deadline
        deadline += 1_000_000
        while time.perf_counter_ns() < deadline:
            pass

    return wait


def port_sides(codec: str, dof: int, ticks: int, pace: str) -> dict[str, float]:
    """Each side's port per tick (µs, median of the ticks after the first 100), as ``bench.tick``
    times it: back to back (``hot``: caches and predictors hot), one tick a millisecond on the
    real loop's scheduler (``paced``: sleep, spin, tick) as the processes run it, or one a
    millisecond busy-waiting in between (``spun``: never idle, so what a paced tick loses that a
    spun one loses too is not the sleep's doing)."""
    ticker = Ticker(period_ns=1_000_000, spin_ns=100_000, min_spin_ns=100_000)
    ticker.start(time.monotonic_ns() + 1_000_000)
    pair = _port_pair(codec, dof, ticks, "protocol")
    wait = {"hot": None, "paced": ticker.wait, "spun": _spun()}[pace]
    t_op, t_to = port_side_ticks(*pair, ticks, wait)
    return {
        "operator": statistics.median(t_op[100:]) / 1e3,
        "teleoperator": statistics.median(t_to[100:]) / 1e3,
    }


def run_case(codec: str, dof: int, duration: float, tmp: Path) -> dict[str, Any]:
    site, probe = tmp / f"site-{codec.replace(':', '')}", tmp / f"probe-{codec.replace(':', '')}"
    site.mkdir()
    probe.mkdir()
    (site / "sitecustomize.py").write_text(SITE)
    out = tmp / f"run-{codec.replace(':', '')}"
    report = probed_run(ROOT, site, {"TELEOP_PHASES": str(probe)}, codec, dof, duration, out)
    case: dict[str, Any] = {
        "codec": codec,
        "dof": dof,
        "port_us": {pace: port_sides(codec, dof, 3000, pace) for pace in ("hot", "paced", "spun")},
    }
    for f in probe.glob("phases-*.json"):
        doc = json.loads(f.read_text())
        if doc["role"] not in ("operator", "teleoperator"):
            continue
        loop = report["processes"][doc["role"]]["loop"]
        case[doc["role"]] = {
            "us_per_tick": figures(doc, loop["ticks"]),
            "cpu_fraction": loop["cpu_fraction"],  # with the probe's reads: a little above bench.cpu's
            "spin_us": loop.get("spin_us"),
            "clock_read_ns": doc["clock_read_ns"],
        }
    return case


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.phases", description=__doc__.split("\n\n")[0])
    ap.add_argument("--codecs", nargs="+", default=["none", "eds:50", "pdp:1"])
    ap.add_argument("--dof", type=int, default=2)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--out", default="bench/results/phases.json")
    a = ap.parse_args(argv)
    started = time.time()
    with tempfile.TemporaryDirectory(prefix="teleop-phases-") as t:
        cases = [run_case(c, a.dof, a.duration, Path(t)) for c in a.codecs]
    doc = {
        "what": "CPU per tick of each phase of teleop run's loops (us), probe reads taken off",
        "python": platform.python_version(),
        "duration_s": a.duration,
        "cases": cases,
        "wall_s": round(time.time() - started, 1),
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(doc, indent=2) + "\n")
    for c in cases:
        for role in ("operator", "teleoperator"):
            f = c[role]["us_per_tick"]
            parts = "  ".join(f"{k} {v:.1f}" for k, v in f.items())
            print(f"{c['codec']:<7} {c['dof']} DoF {role:<12} {parts}")
            hot, paced = (c["port_us"][m][role] for m in ("hot", "paced"))
            print(f"{'':<7} port tick alone: back to back {hot:.1f} us, paced at 1 kHz {paced:.1f} us")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
